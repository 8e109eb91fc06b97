"""`python -m service pipelines`: each pipeline with its required and optional layers and its options."""

from __future__ import annotations

import argparse
import json


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    from service import pipelines

    infos = pipelines.describe()
    if args.json:
        print(json.dumps(infos, indent=2))
        return 0
    for info in infos:
        flag = " (temporal)" if info["temporal"] else ""
        default = " [default]" if info["name"] == pipelines.DEFAULT else ""
        print(f"{info['name']}{flag}{default}: {info['summary']}")
        print(f"    requires: {', '.join(info['requires']) or '-'}")
        print(f"    optional: {', '.join(info['optional']) or '-'}")
        for option, spec in info["option_specs"].items():
            print(f"    option {option} = {json.dumps(spec['default'])}: {spec['allowed']}")
    return 0
