"""`python -m service denoise`: every frame of a sequence folder through one pipeline state, in order;
prints per-frame milliseconds, relL2 of input and output (frames with a `reference`) and repaired values."""

from __future__ import annotations

import argparse

from service.cli.sequence_args import (
    add_sequence_args,
    channel_map,
    parse_options,
    resolve_pipeline,
)


def add_args(p: argparse.ArgumentParser) -> None:
    add_sequence_args(p)
    p.add_argument("--png", action="store_true", help="also write tone-mapped PNG previews")
    p.add_argument("--keep-layers", action="store_true",
                   help="write each input file's channels plus the result (Blender: a Denoised pass of the view layer; "
                        "else denoised.R G B) instead of the result alone")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from service import pipelines
    from service.sequence import denoise_folder
    from service.warmup import CompileNotice

    options = parse_options(args.option)
    if args.online:
        options["online"] = True  # a pipeline without this option refuses it: "has no option 'online'"
    mapping = channel_map(args)
    name = resolve_pipeline(args.pipeline, args.in_dir, mapping, args.view_layer, args.second_half is not None)
    pipeline = pipelines.get(name, **options)
    print(f"{'frame':<24} {'ms':>9} {'relL2 in':>10} {'relL2 out':>10} {'NaN/Inf':>8}", flush=True)
    results = []
    with CompileNotice(pipeline.name) as notice:  # a frame's ms include any kernels compiled for it
        for r in denoise_folder(pipeline, args.in_dir, args.out_dir, png=args.png, channel_map=mapping,
                                view_layer=args.view_layer, second_half=args.second_half,
                                keep_layers=args.keep_layers):
            notice.report()
            results.append(r)
            noisy = "" if r.rel_l2_noisy is None else f"{r.rel_l2_noisy:.4f}"
            out = "" if r.rel_l2_out is None else f"{r.rel_l2_out:.4f}"
            print(f"{r.name:<24} {r.ms:>9.1f} {noisy:>10} {out:>10} {r.nonfinite:>8}", flush=True)
    ms = [r.ms for r in results]
    line = f"{pipeline.name}: {len(results)} frames, median {np.median(ms):.1f} ms/frame (mean {np.mean(ms):.1f})"
    scored = [r for r in results if r.rel_l2_out is not None]
    if scored:
        noisy = np.mean([r.rel_l2_noisy for r in scored])
        out = np.mean([r.rel_l2_out for r in scored])
        line += f", relL2 (0.1% trimmed) {noisy:.4f} -> {out:.4f}"
    print(line)
    if results and results[-1].online is not None:
        status = results[-1].online
        print(f"online training: {status['state']}, {status['frames_trained']} frames trained, "
              f"{status['frames_dropped']} dropped, weights version {status['weights_version']}"
              + (f", last error: {status['last_error']}" if status.get("last_error") else ""))
    print(f"outputs in {args.out_dir}")
    return 0
