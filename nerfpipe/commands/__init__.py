"""Layer 3: one module per CLI subcommand (thin wrappers over the library)."""
