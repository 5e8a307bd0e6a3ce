"""Physics-based texture (paper Sec. 3.1, Eq. 1-2): the Lambert + Cook-Torrance/GGX BRDF shared by the Mitsuba plugins
and the UV-space renderer, the UV atlas, per-LED visibility, texel shading, rasterisation into cameras, the
near-field point light, the batch relighter, and the one module where tensors cross Dr.Jit <-> torch (bridge)."""
