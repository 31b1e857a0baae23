"""The house's measures (issue 18): longest modules and functions, effect names outside
``mechanics/effects``.

    python bench/house.py [--max-module 400] [--max-function 80]

Prints the modules and functions over the limits and every effect name used as one outside
``mechanics/effects/`` (:func:`effect_name_uses`: the diagnosis, the problem builder and the
truth model loop over what effects declare, not over names); writes
``bench/results/house.json``; exits 1 when anything is over.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("imaging", "registration", "meshing", "mechanics", "breastmodel")


#: An expression whose source matches this is an effects mapping (``effects``,
#: ``model["effects"]``, ``self.effects``, ``EFFECTS``, ``eff``).
EFFECTS_MAPPING = re.compile(r"(?i)\beff|effects\b|\[.effects.\]")
LOOKUPS = ("get", "pop", "setdefault")


def _is_effects(node: ast.AST) -> bool:
    return bool(EFFECTS_MAPPING.search(ast.unparse(node)))


def _literals(node: ast.AST | None, names) -> list[ast.Constant]:
    """String constants equal to an effect name: ``node`` itself, or the elements of a
    tuple, list or set literal (the keys of a dict literal)."""
    if isinstance(node, ast.Constant):
        return [node] if isinstance(node.value, str) and node.value in names else []
    elts = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None)
    if not isinstance(node, ast.Tuple | ast.List | ast.Set | ast.Dict) or elts is None:
        return []
    return [e for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)
            and e.value in names]


def effect_name_uses(source: str, names) -> list[tuple[int, str, str]]:
    """Where a module uses a registered effect's name as an effect name, with the rule.

    A string literal equal to an effect name counts when it is
    ``compare``: an operand of ``==`` or ``!=``;
    ``member``: tested with ``in`` / ``not in`` against an effects mapping, or an element of a
    literal tuple, list or set that something is tested against;
    ``lookup``: a subscript read, or the first argument of ``get``, ``pop`` or
    ``setdefault``, of an effects mapping (:data:`EFFECTS_MAPPING`);
    ``loop``: an element of a literal collection a ``for`` iterates over;
    ``constant``: an element (or dict key) of a collection literal bound to a module-level
    name, when at least two elements are given and all are effect names (a list of special
    effects).
    Not counted: writing a configuration (keys of a dict literal, subscript stores), set
    names (``mesh.face_sets["skin"]``, ``"fixed" in mesh.node_sets``), metric and file keys.

    Returns
    -------
    [(line, name, rule)]
    """
    tree = ast.parse(source)
    out: list[tuple[int, str, str]] = []

    def add(nodes, rule):
        out.extend((c.lineno, c.value, rule) for c in nodes)

    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            for k, op in enumerate(node.ops):
                left, right = operands[k], operands[k + 1]
                if isinstance(op, ast.Eq | ast.NotEq):
                    add(_literals(left, names) if isinstance(left, ast.Constant) else [], "compare")
                    add(_literals(right, names) if isinstance(right, ast.Constant) else [],
                        "compare")
                elif isinstance(op, ast.In | ast.NotIn):
                    if _is_effects(right):
                        add(_literals(left, names), "member")
                    if not isinstance(right, ast.Constant):
                        add(_literals(right, names), "member")
        elif isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load):
            if _is_effects(node.value) and isinstance(node.slice, ast.Constant):
                add(_literals(node.slice, names), "lookup")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in LOOKUPS and node.args and _is_effects(node.func.value):
                add(_literals(node.args[0], names) if isinstance(node.args[0], ast.Constant)
                    else [], "lookup")
        elif isinstance(node, ast.For | ast.comprehension):
            add(_literals(node.iter, names), "loop")
    for node in tree.body:
        value = node.value if isinstance(node, ast.Assign | ast.AnnAssign) else None
        if isinstance(value, ast.Tuple | ast.List | ast.Set | ast.Dict):
            elts = value.keys if isinstance(value, ast.Dict) else value.elts
            found = _literals(value, names)
            if len(elts) >= 2 and len(found) == len(elts):
                add(found, "constant")
    return sorted(set(out))


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node.name, node.lineno, node.end_lineno - node.lineno + 1


def measure(max_module: int, max_function: int) -> dict:
    sys.path.insert(0, str(ROOT))
    from mechanics.effects import EFFECTS

    names = set(EFFECTS)
    modules, functions, literals = [], [], []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            text = path.read_text(encoding="utf-8")
            n = len(text.splitlines())
            if n > max_module:
                modules.append((rel, n))
            tree = ast.parse(text)
            functions += [(f"{rel}:{line} {name}", length)
                          for name, line, length in _functions(tree) if length > max_function]
            if rel.startswith("mechanics/effects/"):
                continue
            literals += [f"{rel}:{line} {name!r} ({rule})"
                         for line, name, rule in effect_name_uses(text, names)]
    return {"max_module": max_module, "max_function": max_function,
            "modules_over": sorted(modules, key=lambda t: -t[1]),
            "functions_over": sorted(functions, key=lambda t: -t[1]),
            "effect_name_literals": literals}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max-module", type=int, default=400)
    ap.add_argument("--max-function", type=int, default=80)
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "house.json")
    args = ap.parse_args(argv)
    res = measure(args.max_module, args.max_function)
    print(f"modules over {args.max_module} lines: {len(res['modules_over'])}")
    for rel, n in res["modules_over"]:
        print(f"  {n:5d}  {rel}")
    print(f"functions over {args.max_function} lines: {len(res['functions_over'])}")
    for rel, n in res["functions_over"]:
        print(f"  {n:5d}  {rel}")
    print(f"effect names used as effect names outside mechanics/effects: "
          f"{len(res['effect_name_literals'])}")
    for s in res["effect_name_literals"]:
        print(f"  {s}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=1) + "\n")
    over = res["modules_over"] or res["functions_over"] or res["effect_name_literals"]
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
