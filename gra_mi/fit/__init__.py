"""Material fitting (paper Sec. 3.1, Eq. 3): per-texel UV albedo and roughness from a capture."""
