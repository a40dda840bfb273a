"""``warpsim list``: the scenes, their descriptions and settable parameters."""
from __future__ import annotations

READ_ONLY = True
"""Writes nothing: run outside the command's output-lock scope."""


def add_parser(sub):
    sub.add_parser("list", help="list the scenes and their parameters")


def run(args, out, err):
    from ..scenes import format_value, scenes

    registry = scenes()
    width = max((len(n) for n in registry), default=0)
    for name, cls in registry.items():
        print(f"{name:<{width}}  {cls.description}", file=out)
        for key, param in cls.params.items():
            choices = f" ({'|'.join(map(str, param.choices))})" if param.choices else ""
            print(f"    {key}={format_value(param.default)}  {param.help}{choices}", file=out)
    print("\nRun one with: warpsim run SCENE [--frames N] [--set KEY=VALUE ...]", file=out)
    return 0

