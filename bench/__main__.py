"""`python -m bench ...`: benchmark commands.

    run --sequences DIR... [--pipelines all] [--anchors oidn] --out REPORT_DIR
        every pipeline and the anchors on the same frames: results.json, report.md, pareto.png, report.html
    scaling [--pipelines all] [--anchors oidn] [--sizes 128x128,...] [--out DIR]
        ms per megapixel and peak memory at 128x128 ... 1920x1080
    stability [--pipelines all] [--anchors none] [--size WxH]
        hard-case pass/fail matrix; exit status 1 on any failure
    synthetic --out DIR
        write the analytic synthetic sequence (all layers + reference)

Thread counts are fixed (bench.environment) before any numeric library loads, so every method in a run
works under the same setting; `--threads` changes it (default: every CPU this process may use).
"""

import argparse
import sys
from pathlib import Path


def _size(text: str) -> tuple[int, int]:
    """'WxH' -> (width, height)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size '{text}' is not WxH") from None
    return width, height


def _names(text: str) -> list[str]:
    return [n for n in text.replace(",", " ").split() if n]


def _methods(values: list[str]) -> list[str]:
    """--pipelines values: names separated by spaces or commas, or one pipeline with options per value
    (`NAME:KEY=VALUE,KEY=VALUE`, whose commas separate options)."""
    return [n for v in values for n in ([v] if ":" in v else _names(v))]


def cmd_run(args: argparse.Namespace) -> int:
    from bench.methods import select
    from bench.report import overall_table, write_all
    from bench.run import benchmark

    methods = select(None if args.pipelines is None else _methods(args.pipelines), args.anchors)
    print(f"methods: {', '.join(m.name for m in methods)}; sequences: {', '.join(map(str, args.sequences))}")
    command = ["python", "-m", "bench", *sys.argv[1:]]
    results, runs = benchmark(args.sequences, methods, flip=not args.no_flip, repeats=args.repeats, command=command)
    paths = write_all(results, runs, args.out)
    print(overall_table(results["overall"]))
    for seq in results["sequences"]:
        for name, record in seq["results"].items():
            if record["status"] != "ok":
                print(f"{seq['name']} / {name}: {record['status']}: {record['note']}")
    print(f"wrote {', '.join(str(p) for p in paths.values())} in {results['wall_seconds']:.0f} s")
    return 0


def cmd_scaling(args: argparse.Namespace) -> int:
    import json

    from bench import environment
    from bench.methods import select
    from bench.scaling import SIZES, plot, run_scaling, table

    methods = [m.name for m in select(args.pipelines, args.anchors) if m.name != "noisy"]
    records = run_scaling(methods, tuple(args.sizes or SIZES), frames=args.frames)
    text = table(records)
    print(text)
    for rec in records:
        if "error" in rec:
            print(f"{rec['method']} {rec['width']}x{rec['height']}: {rec['error']}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scaling.json").write_text(json.dumps({"environment": environment.describe(), "records": records},
                                                      indent=1))
    (args.out / "scaling.md").write_text(
        "# Resolution scaling\n\nms per megapixel (median ms per frame; peak memory: traced by one step / "
        "process RSS incl. warm-up, MiB)\n\n" + text + "\n\n![scaling](scaling.png)\n"
    )
    plot(records, args.out / "scaling.png")
    print(f"wrote {args.out}/scaling.json, scaling.md, scaling.png")
    return 0


def cmd_stability(args: argparse.Namespace) -> int:
    from bench.methods import select
    from bench.stability import CASES, matrix, run_suite

    methods = select(args.pipelines, args.anchors)
    cases = tuple(c for c in CASES if not args.cases or c.name in args.cases)
    width, height = args.size
    results = run_suite(methods, height=height, width=width, frames=args.frames, cases=cases)
    print(matrix(results))
    failed = sum(not r.passed for row in results.values() for r in row.values())
    print(f"{failed} failure(s) in {len(methods)} method(s) x {len(cases)} case(s)")
    return 1 if failed else 0


def cmd_synthetic(args: argparse.Namespace) -> int:
    from bench.synthetic import write_synthetic_sequence

    width, height = args.size
    paths = write_synthetic_sequence(args.out, height=height, width=width, frames=args.frames, spp=args.spp,
                                     seed=args.seed)
    print(f"wrote {len(paths)} frames to {args.out}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=None, help="worker threads of every library (default: all)")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="every pipeline and the anchors on the same sequences; writes the report")
    run.add_argument("--sequences", type=Path, nargs="+", required=True, help="sequence folders (EXR + reference)")
    run.add_argument("--pipelines", nargs="+", default=None,
                     help="names, 'all' (default) or 'none'; NAME:KEY=VALUE,... runs a pipeline with options")
    run.add_argument("--anchors", type=_names, default=None, help="noisy, oidn-high, oidn-fast, oidn, all (default)")
    run.add_argument("--out", type=Path, required=True, help="report folder")
    run.add_argument("--no-flip", action="store_true", help="skip FLIP (the slowest metric)")
    run.add_argument("--repeats", type=int, default=3, help="timed passes per sequence and method (median of all)")
    run.set_defaults(func=cmd_run)

    sca = sub.add_parser("scaling", help="ms per megapixel and peak memory from 128x128 to 1920x1080")
    sca.add_argument("--pipelines", type=_names, default=None)
    sca.add_argument("--anchors", type=_names, default=["oidn"])
    sca.add_argument("--sizes", type=lambda t: [_size(s) for s in _names(t)], default=None, help="WxH,WxH,...")
    sca.add_argument("--frames", type=int, default=3, help="timed frames per size (after one warm-up)")
    sca.add_argument("--out", type=Path, default=Path("out/bench/scaling"))
    sca.set_defaults(func=cmd_scaling)

    sta = sub.add_parser("stability", help="hard-case pass/fail matrix for every pipeline")
    sta.add_argument("--pipelines", type=_names, default=None)
    sta.add_argument("--anchors", type=_names, default=["none"], help="also run anchors (default none)")
    sta.add_argument("--cases", type=_names, default=None, help="subset of case names")
    sta.add_argument("--size", type=_size, default=(64, 48), help="WxH of the cases without a fixed size")
    sta.add_argument("--frames", type=int, default=3)
    sta.set_defaults(func=cmd_stability)

    syn = sub.add_parser("synthetic", help="write the analytic synthetic sequence (all layers + reference)")
    syn.add_argument("--out", type=Path, required=True)
    syn.add_argument("--size", type=_size, default=(96, 64), help="WxH")
    syn.add_argument("--frames", type=int, default=4)
    syn.add_argument("--spp", type=int, default=8)
    syn.add_argument("--seed", type=int, default=0)
    syn.set_defaults(func=cmd_synthetic)

    args = parser.parse_args()
    from bench.environment import configure_threads
    from service.process import configure

    configure_threads(args.threads)
    configure()
    return args.func(args)


sys.exit(main())
