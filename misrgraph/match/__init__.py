"""Image matching: NCC and least-squares matching (lsm), the MISR matching pipeline (pipeline)."""
