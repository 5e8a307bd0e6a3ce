"""The video refiner (paper Sec. 3.3): diffusers' WAN2.1-VACE with LoRA and atemporal envmap attention (model), latent
flow matching and the Euler sampler (flow), sequences on disk (data), training with error recycling (train) and
rolling-window refinement of any length (infer)."""
