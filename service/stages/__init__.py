"""Classical numpy stages: pure functions on (H, W, C) float32 arrays, one module per stage."""
