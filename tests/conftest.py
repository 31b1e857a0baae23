"""Shared fixtures: a zoo of tiny meshes lives in tests/zoo.py."""

import matplotlib

matplotlib.use("Agg")
