"""Finite-element mechanics of soft tissue: plain arrays in, plain state out (numpy/scipy only)."""
