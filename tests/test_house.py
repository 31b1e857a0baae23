"""The house's rule on effect names: outside ``mechanics/effects/`` no library module uses a
registered effect's name as an effect name (``bench/house.py``'s :func:`effect_name_uses`
says what counts); what callers need to know about an effect it declares."""

from pathlib import Path

import pytest

from bench.house import PACKAGES, effect_name_uses
from mechanics.effects import EFFECTS

ROOT = Path(__file__).resolve().parents[1]
NAMES = set(EFFECTS)


@pytest.mark.parametrize("source,rules", [
    ('if name == "tied":\n    pass', ["compare"]),
    ('ok = "sliding" in self.effects', ["member"]),
    ('ok = k in ("sliding", "tied")', ["member", "member"]),
    ('t = model["effects"]["skin"]', ["lookup"]),
    ('t = eff.pop("sliding", None)', ["lookup"]),
    ('for n in ("skin", "fascia"):\n    pass', ["loop", "loop"]),
    ('SPECIAL = ("sliding", "tied")', ["constant", "constant"]),
    ('REASONS = {"gravity": "a", "fixed": "b"}', ["constant", "constant"]),
])
def test_uses_as_effect_names_are_found(source, rules):
    assert sorted(r for _, _, r in effect_name_uses(source, NAMES)) == sorted(rules)


@pytest.mark.parametrize("source", [
    'f = mesh.face_sets["skin"]',
    'ok = "fixed" in mesh.node_sets',
    'cfg = {"effects": {"skin": {"E": 4.0}, "fixed": {"node_set": "fixed"}}}',
    'effects["gravity"] = {"direction": (0, 0, -1)}',
    'r = metrics.get("regions", {})',
    'TISSUES = ("air", "fat", "skin")',
])
def test_set_names_and_configurations_are_not_effect_names(source):
    assert effect_name_uses(source, NAMES) == []


def test_no_effect_name_outside_the_effects_package():
    found = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if not rel.startswith("mechanics/effects/"):
                text = path.read_text(encoding="utf-8")
                found += [f"{rel}:{line} {name!r} ({rule})"
                          for line, name, rule in effect_name_uses(text, NAMES)]
    assert found == []


def test_no_module_over_400_lines_and_no_function_over_80():
    """The house's size limits (issue 18), as ``python bench/house.py`` measures them."""
    from bench.house import measure

    res = measure(400, 80)
    assert res["modules_over"] == [] and res["functions_over"] == [], res


def test_files_are_replaced_only_by_the_one_atomic_writer():
    """Outside ``imaging/atomic.py`` nothing renames a temporary file onto an output, but
    registration's own copy (it imports no other stage) and the stage cache, which renames
    whole folders."""
    allowed = {"imaging/atomic.py", "registration/transforms.py", "breastmodel/cache.py"}
    found = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            text = path.read_text(encoding="utf-8")
            if rel not in allowed and ("os.replace(" in text or "os.rename(" in text):
                found.append(rel)
    assert found == []
