"""Diagnosis of a fitted model: where it fails, which physical effect is missing.

- :func:`load_run`: a finished ``breastmodel run`` folder as arrays.
- :func:`failure_map`, :func:`failure_tables`, :func:`skin_regions`: where it fails.
- :func:`rank_candidates`: which registered effect (or fixed parameter) explains the residual;
  :func:`answer`: its first significant candidate, or None.
- :func:`diagnose`: both, written to ``diagnosis.json`` / ``diagnosis.html``.
- :func:`compare_runs`, :func:`write_compare`: model revisions side by side.
"""

from breastmodel.diagnosis.compare import compare_runs, write_compare
from breastmodel.diagnosis.diagnose import diagnose
from breastmodel.diagnosis.maps import failure_map, failure_tables, skin_regions
from breastmodel.diagnosis.missing import rank_candidates
from breastmodel.diagnosis.rundata import RunData, load_run
from breastmodel.diagnosis.scoring import answer

__all__ = ["RunData", "answer", "compare_runs", "diagnose", "failure_map", "failure_tables",
           "load_run", "rank_candidates", "skin_regions", "write_compare"]
