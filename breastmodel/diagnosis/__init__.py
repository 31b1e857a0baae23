"""Diagnosis of a fitted model: where it fails, which physical effect is missing."""

from breastmodel.diagnosis.rundata import RunData, load_run

__all__ = ["RunData", "load_run"]
