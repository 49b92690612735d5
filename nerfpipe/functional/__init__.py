"""Layer 1: pure tensor functions (no state, no I/O). Nothing here imports an upper layer."""
