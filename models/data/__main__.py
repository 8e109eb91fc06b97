"""`python -m models.data COMMAND`: render sequences with Mitsuba 3, list scenes, build the training set.

  render   --scene NAME --frames N --spp N --ref-spp N --size WxH --seed S --out DIR [--half]
  scenes   list the library with what each scene stresses
  dataset  --out DIR [--sequences-per-scene N --frames N --size WxH --spp N [N ...] --ref-spp N]: the training set
  report   DIR...: noisy relL2 and motion/motionDual warp errors of rendered sequence folders
  variant  print the Mitsuba variant this machine renders with
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from models.data import scenes
from service.process import configure


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, e.g. 256x256, got '{text}'") from None
    return w, h


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m models.data", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render", help="render one sequence folder")
    render.add_argument("--scene", required=True, choices=list(scenes.SCENES))
    render.add_argument("--frames", type=int, default=8)
    render.add_argument("--spp", type=int, default=4, help="noisy samples per pixel (separate 1-spp passes)")
    render.add_argument("--ref-spp", type=int, default=1024)
    render.add_argument("--size", type=_size, default=(256, 256), help="WxH pixels")
    render.add_argument("--seed", type=int, default=0, help="noise and animation-variation seed (0: canonical)")
    render.add_argument("--out", required=True)
    render.add_argument("--half", action="store_true", help="write float16 channels")
    render.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda > llvm > scalar)")
    sub.add_parser("scenes", help="list the scene library")
    data = sub.add_parser("dataset", help="render the training set, skipping finished sequences")
    data.add_argument("--out", required=True)
    data.add_argument("--sequences-per-scene", type=int, default=4)
    data.add_argument("--frames", type=int, default=8)
    data.add_argument("--size", type=_size, default=(128, 128))
    data.add_argument("--spp", type=int, nargs="+", default=[2, 4, 8],
                      help="noisy samples per pixel, cycled over the sequences (each >= 2)")
    data.add_argument("--ref-spp", type=int, default=1024)
    data.add_argument("--half", action="store_true")
    data.add_argument("--first-seed", type=int, default=2, help="first variation seed (>= 2; 0 and 1 are held out)")
    report = sub.add_parser("report", help="noise and warp errors of sequence folders")
    report.add_argument("folders", nargs="+")
    report.add_argument("--json", action="store_true")
    sub.add_parser("variant", help="print the Mitsuba variant in use")
    return parser


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    args = _parser().parse_args(argv)
    if args.command == "scenes":
        for spec in scenes.SCENES.values():
            print(f"{spec.name:14s} {spec.stresses}")
        return 0
    if args.command == "variant":
        from models.data.variant import choose_variant

        print(choose_variant())
        return 0
    if args.command == "report":
        return _report(args.folders, args.json)
    if args.command == "dataset":
        from models.data.dataset import DatasetOptions, render_dataset

        opts = DatasetOptions(args.sequences_per_scene, args.frames, *args.size, tuple(args.spp), args.ref_spp,
                              args.half, args.first_seed)
        done = [seconds for _job, seconds in render_dataset(args.out, opts)]
        print(f"rendered {len(done)} sequences in {sum(done):.0f} s into {args.out}")
        return 0
    return _render(args)


def _render(args: argparse.Namespace) -> int:
    from models.data.render import RenderOptions
    from models.data.sequence import render_sequence

    try:
        opts = RenderOptions(*args.size, args.spp, args.ref_spp, seed=args.seed)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    start = time.perf_counter()

    def step(index: int, seconds: float) -> None:
        print(f"frame {index:4d}: {seconds:6.2f} s", file=sys.stderr)

    render_sequence(scenes.get(args.scene), args.out, opts, args.frames, half=args.half, variant=args.variant,
                    on_frame=step)
    print(f"{args.scene}: {args.frames} frames in {time.perf_counter() - start:.1f} s -> {args.out}")
    return 0


def _report(folders: list[str], as_json: bool) -> int:
    from models.data.evaluate import sequence_report

    rows = {folder: sequence_report(folder) for folder in folders}
    if as_json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'sequence':30s} {'s/frame':>8s} {'noisy':>8s} {'trim':>8s} {'static':>8s} {'motion':>8s} {'dual':>8s}"
          f" {'disocc%':>8s} {'m@dis':>8s} {'d@dis':>8s}")
    for folder, r in rows.items():
        print(f"{folder[-30:]:30s} {r.get('seconds_per_frame', float('nan')):8.2f} {r['noisy_rel_l2']:8.4f} "
              f"{r['noisy_rel_l2_trimmed']:8.4f} {r.get('static', float('nan')):8.4f} "
              f"{r.get('motion', float('nan')):8.4f} {r.get('dual', float('nan')):8.4f} "
              f"{100 * r.get('disoccluded_fraction', float('nan')):8.2f} "
              f"{r.get('motion_disoccluded', float('nan')):8.4f} {r.get('dual_disoccluded', float('nan')):8.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
