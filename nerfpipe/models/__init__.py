"""Layer 2: radiance-field models (stateful ``nn.Module``s) and their registry."""
