"""The demo's phantom: a small subject with a hidden effect whose truth FEBio computed.

``breastmodel demo`` tells the toolkit's story on this subject: the bulk model (one breast
modulus) is fitted, the report shows where it fails, the diagnosis names the missing effect,
the refit with it lowers the error. The truth has **different moduli in the left and the
right breast** (``PHYSICS["asymmetric"]``: 0.7 and 1.4 times ``breast_E_kpa``), which FEBio
expresses exactly (two Neo-Hookean materials on one conforming mesh, no shell or spring
approximation), and which the fitted model, with one modulus tied across both breasts, lacks;
its candidate name in the diagnosis is :data:`HIDDEN_EFFECT`.

A user's machine has no FEBio, so the subject ships in the repository
(``breastmodel/demo_data/``, about 1 MB: compressed NIfTI volumes, the truth label maps, the
truth mesh and displacements); :func:`make_demo_data` regenerates it with FEBio
(``breastmodel demo --regenerate-data``). The truth is solved on its own 5 mm mesh of the
stress-free anatomy; the fit meshes the registered supine label map at its own size (8 mm by
default), so the fitted mesh is not the truth's (no inverse crime).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

__all__ = ["DEMO_DATA", "DEMO_SPEC", "HIDDEN_EFFECT", "demo_spec", "make_demo_data"]

#: Folder of the shipped demo subject: ``subject/`` (the pipeline's input) and
#: ``subject_truth/`` (the truth: label maps, mesh, displacements, physics).
DEMO_DATA = Path(__file__).resolve().parents[1] / "demo_data"
#: :func:`~breastmodel.phantom.family.draw_spec` arguments of the demo subject: seed 1 (a
#: muscle slab fixed behind, 1.5 mm voxels, prone / supine / supine tilted 20 deg), cup C and a
#: soft breast (0.3 kPa) so that gravity moves the half-size breasts by millimetres, not tenths.
DEMO_SPEC: dict[str, Any] = {"seed": 1, "size": "small", "physics": "asymmetric", "cup": "C",
                             "breast_E_kpa": 0.3}
#: The diagnosis candidate that the truth has and the fitted model lacks.
HIDDEN_EFFECT = "regions:asymmetry"


def demo_spec():
    """The demo subject's :class:`~breastmodel.phantom.family.SubjectSpec`."""
    from breastmodel.phantom.family import draw_spec

    kw = dict(DEMO_SPEC)
    return draw_spec(kw.pop("seed"), size=kw.pop("size"), **kw)


def make_demo_data(out: str | Path = DEMO_DATA, *, febio: str | Path | None = None,
                   cache_dir: str | Path | None = None, progress: bool = True) -> Path:
    """(Re)write the demo subject with its truth computed by FEBio.

    Parameters
    ----------
    out
        Folder to write (default: the shipped :data:`DEMO_DATA`); ``out/subject`` and
        ``out/subject_truth`` are replaced.
    febio
        FEBio executable (default: ``$FEBIO`` or the known places, see
        :mod:`breastmodel.febio`).
    cache_dir
        Cache of truth meshes and solutions (None: none).
    progress
        Log the stages.

    Returns
    -------
    Path
        ``out``.
    """
    from breastmodel.config import write_json
    from breastmodel.phantom.family import make_subject

    out = Path(out)
    spec = demo_spec()
    tmp = out / ".regenerating"
    shutil.rmtree(tmp, ignore_errors=True)
    make_subject(spec, tmp / "subject", truth_solver="febio", febio=febio, cache_dir=cache_dir,
                 progress=progress)
    (tmp / "subject_truth" / "timings.json").unlink(missing_ok=True)  # machine-dependent
    for name in ("subject", "subject_truth"):
        shutil.rmtree(out / name, ignore_errors=True)
        (tmp / name).rename(out / name)
    shutil.rmtree(tmp)
    write_json(out / "demo.json", {"spec": spec.to_dict(), "hidden_effect": HIDDEN_EFFECT,
                                   "truth_solver": "febio",
                                   "regenerate": "breastmodel demo --regenerate-data"})
    return out
