"""`python -m service stream`: a sequence folder through a running service's WebSocket session, the
results written like `denoise`'s."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from service.cli.sequence_args import (
    add_sequence_args,
    channel_map,
    parse_options,
    resolve_pipeline,
)


def add_args(p: argparse.ArgumentParser) -> None:
    add_sequence_args(p)
    p.add_argument("--url", default="http://127.0.0.1:8000", help="service url (default http://127.0.0.1:8000)")
    p.add_argument("--api-key", default=os.environ.get("MCDENOISE_API_KEY"),
                   help="API key (default: $MCDENOISE_API_KEY)")
    p.add_argument("--window", type=int, default=4, help="frames sent ahead of the answers (default 4)")


def run(args: argparse.Namespace) -> int:
    from service.client import Client, ServiceError
    from service.exr import list_sequence, read_header

    options = parse_options(args.option)
    mapping = channel_map(args)  # checked here; the session's server reads the frames with it
    name = resolve_pipeline(args.pipeline, args.in_dir, mapping, args.view_layer, args.second_half is not None)
    first = read_header(list_sequence(args.in_dir)[0], mapping, args.view_layer)
    map_json = json.loads(args.channel_map.read_text()) if args.channel_map else None
    try:
        with Client(args.url, args.api_key) as client, client.session(
            name, first.width, first.height, options=options, online=args.online, channel_map=map_json,
            view_layer=args.view_layer,
        ) as session:
            start = time.perf_counter()
            results = session.stream_folder(args.in_dir, args.out_dir, window=args.window,
                                             second_half=args.second_half)
            seconds = time.perf_counter() - start
            status = session.status()
    except ServiceError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for r in results:
        print(f"{r.name:<24} {'ok' if r.error is None else f'error {r.error.code}: {r.error.message}'}")
    failed = sum(r.error is not None for r in results)
    print(f"{name}: {len(results) - failed}/{len(results)} frames in {seconds:.2f} s "
          f"({len(results) / seconds:.1f} frames/s), step mean {status['mean_ms']} ms, p95 {status['p95_ms']} ms")
    print(f"outputs in {args.out_dir}")
    return 2 if failed else 0
