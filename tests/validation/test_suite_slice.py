"""The CI slice of the validation suite: three small subjects from the phantom family, their
truth computed by FEBio, each run through the whole pipeline (own segmentation; truth labels).

It asserts that the suite reports every stage of every subject (a stage that stops is a row
with its error, never a crash) and every target of :data:`breastmodel.validation.TARGETS`
that is enforced (their issues have landed); the others are recorded in the printed table
and in ``$BREASTMODEL_VALIDATION_OUT/validation_slice.json`` when that is set.

    pytest -m validation -rP tests/validation          # about 10-15 minutes on 2 cores
"""

import json
import os
from pathlib import Path

import pytest

from breastmodel.validation import ARMS, family_maker, format_table, run_suite

pytestmark = [pytest.mark.slow, pytest.mark.validation]

#: Seeds of the slice: small subjects whose drawn field of view covers the whole torso (3), a
#: coil-cut body (0) and a muscle meeting air (1) (the family draws anatomy, voxels,
#: contrast, motion and tilt from the seed too; these are subjects of bench/validate.py).
SLICE = {3: "torso", 0: "coil", 1: "slab"}


def _febio():
    from breastmodel.febio import find_febio

    try:
        return str(find_febio())
    except (FileNotFoundError, ValueError) as exc:
        pytest.skip(f"FEBio 4 is needed for the validation suite's truths: {exc}")


@pytest.fixture(scope="module")
def slice_results(tmp_path_factory):
    febio = _febio()
    out = os.environ.get("BREASTMODEL_VALIDATION_OUT")
    work = Path(out) if out else tmp_path_factory.mktemp("validation")
    # FEBio truths and truth meshes are cached by their inputs; CI keeps them between runs
    cache = Path(os.environ.get("BREASTMODEL_TRUTH_CACHE") or work / "truth_cache")
    make = family_maker(size="small", febio=febio, cache=cache)
    results = run_suite([f"small-{seed:03d}" for seed in SLICE], make, work)
    for res in results:
        if "info" in res:  # made: the drawn field of view is the one the slice expects
            fov = res["info"]["spec"]["fov"]
            assert fov == SLICE[int(res["subject"].rsplit("-", 1)[1])], res["subject"]
    print()
    print(format_table(results))
    for res in results:
        for t in res.get("targets", []):
            flag = "ENFORCED" if t["enforced"] else "recorded"
            print(f"{res['subject']} issue {t['issue']} {t['arm']}:{t['figure']} = "
                  f"{t['value']} (bound {t['kind']} {t['bound']}): met={t['met']} [{flag}]")
    if out:
        (Path(out) / "validation_slice.json").write_text(json.dumps(results, indent=1))
    return results


def test_every_subject_is_made_and_reports_every_arm(slice_results):
    assert len(slice_results) == len(SLICE)
    for res in slice_results:
        assert "error" not in res, f"{res['subject']}: the subject could not be made: " \
                                   f"{res.get('error')}"
        assert set(res["arms"]) == set(ARMS)
        for arm, a in res["arms"].items():
            assert a["stages"], f"{res['subject']} [{arm}]: no stage ran"
            if a["error"] is None:
                # a completed arm has a fitted modulus and an MHD for every position
                assert a["fitted"]["breast_E"] > 0
                positions = a["calibrate"] + a["held_out"]
                assert set(a["mhd_mm"]) == set(positions)
                assert all(v is not None and v >= 0 for v in a["mhd_mm"].values())
            else:
                # a stage that stopped is named, with the stages before it
                assert a["failed_stage"], f"{res['subject']} [{arm}]: {a['error']}"
                assert a["stages"][-1]["status"] == "failed"


def test_truth_labels_arm_completes(slice_results):
    """With the truth label maps given, the pipeline reaches every prediction."""
    bad = {r["subject"]: r["arms"]["truth_labels"]["error"] for r in slice_results
           if r["arms"]["truth_labels"]["error"] is not None}
    assert not bad, bad


def test_enforced_targets_are_met(slice_results):
    missed = [f"{r['subject']} issue {t['issue']} {t['arm']}:{t['figure']} = {t['value']} "
              f"(bound {t['kind']} {t['bound']})"
              for r in slice_results for t in r["targets"] if t["enforced"] and not t["met"]]
    assert not missed, "\n".join(missed)
