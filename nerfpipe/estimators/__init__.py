"""Layer 2: sample estimators (which points along rays are worth evaluating)."""
