"""``breastmodel effects [NAME]``: the physical effects a model can switch on, from the
registry (a new effect file shows up here without further work)."""

from __future__ import annotations

import argparse
import inspect


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "effects",
        help="list the physical effects, their parameters and options",
        description=(
            "Without NAME: one line per registered effect. With NAME: its description, "
            "options, the mesh sets it needs and its parameters (unit, default, bounds), as "
            "used in the [effects.NAME] table of a model configuration."
        ),
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="an effect to describe in full")
    return p


def describe(name: str | None = None) -> str:
    """The registry as text: a table of effects, or one effect in full."""
    from mechanics.effects import EFFECTS

    if name is None:
        width = max(len(n) for n in EFFECTS)
        return "\n".join(f"{n:<{width}}  {cls.doc}" for n, cls in sorted(EFFECTS.items()))
    if name not in EFFECTS:
        raise ValueError(f"effects: no effect {name!r}; known: {', '.join(sorted(EFFECTS))}")
    cls = EFFECTS[name]
    lines = [f"{name}: {cls.doc}", "", inspect.cleandoc(cls.__doc__ or "")]
    if cls.requires:
        lines += ["", "needs mesh sets: " + ", ".join(cls.requires)]
    if cls.params:
        lines += ["", f"{'parameter':<12} {'unit':<8} {'default':>9} {'bounds':<20} meaning"]
        for p in cls.params:
            bounds = f"[{p.lower:g}, {p.upper:g}]"
            lines.append(f"{p.name:<12} {p.unit:<8} {p.default:>9g} {bounds:<20} {p.doc}")
    if cls.option_specs:
        lines += ["", f"{'option':<18} {'default':<28} meaning"]
        for o in cls.option_specs:
            also = f" (one of {', '.join(map(str, o.choices))})" if o.choices else ""
            lines.append(f"{o.name:<18} {o.default!r:<28} {o.doc}{also}")
    if cls.split_interface:
        lines += ["", "splits the breast-muscle interface into two node layers"]
    if cls.excludes:
        lines += ["excludes: " + ", ".join(cls.excludes)]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    print(describe(args.name))
    return 0
