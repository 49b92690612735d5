"""Layer 2: radiance fields (``nn.Module``s mapping points and directions to density and colour)."""
