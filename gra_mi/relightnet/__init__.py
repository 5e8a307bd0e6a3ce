"""RelightNet (paper Sec. 3.2): the UV-space UNet with environment-map cross-attention (model), the inputs of a view
and inference (infer), training with validation and the ablation (train)."""
