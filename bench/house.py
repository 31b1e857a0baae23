"""The house's measures (issue 18): longest modules and functions, effect names outside
``mechanics/effects``.

    python bench/house.py [--max-module 400] [--max-function 80]

Prints the modules and functions over the limits and every string literal equal to a
registered effect's name found outside ``mechanics/effects/`` (the diagnosis, the problem
builder and the truth model should loop over what effects declare, not name them); writes
``bench/results/house.json``; exits 1 when anything is over.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("imaging", "registration", "meshing", "mechanics", "breastmodel")


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
            text = path.read_text()
            n = len(text.splitlines())
            if n > max_module:
                modules.append((rel, n))
            tree = ast.parse(text)
            functions += [(f"{rel}:{line} {name}", length)
                          for name, line, length in _functions(tree) if length > max_function]
            if rel.startswith("mechanics/effects/"):
                continue
            for node in ast.walk(tree):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) \
                        and node.value in names:
                    literals.append(f"{rel}:{node.lineno} {node.value!r}")
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
    print(f"effect names as string literals outside mechanics/effects: "
          f"{len(res['effect_name_literals'])}")
    for s in res["effect_name_literals"]:
        print(f"  {s}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=1) + "\n")
    over = res["modules_over"] or res["functions_over"] or res["effect_name_literals"]
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
