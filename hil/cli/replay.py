"""``hil replay F.mcap --live [HOST:]PORT``: watch a recorded session as if it ran now."""

from __future__ import annotations

import argparse
import sys
import time

from hil.cli.argtypes import nonnegative_float, positive_float
from hil.cli.recording import add_live_arguments, live_address

LINGER_S = 1.0  # after the last message: let the clients' queues drain before the server stops


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "replay", help="stream a recorded session to Foxglove over WebSocket",
        description="Serve a recorded session (one file or a split series, finished or "
        "truncated: what can be read is served) over the Foxglove WebSocket protocol, every "
        "message at its recorded pace scaled by --speed, with the topics and JSON schemas of "
        "a live run (CDR topics are served as JSON).")
    parser.add_argument("session", metavar="F.mcap", help="session file, series or folder")
    parser.add_argument("--speed", type=nonnegative_float, default=1.0, metavar="X",
                        help="X times real time (default 1; 0: as fast as possible)")
    parser.add_argument("--wait", type=positive_float, metavar="S",
                        help="wait up to S seconds for a client to subscribe before streaming")
    add_live_arguments(parser, tuning=False)
    parser.set_defaults(handler=replay_command)


def replay_command(args: argparse.Namespace) -> int:
    from hil.core.recording.live import LiveSink, announce, parse_address
    from hil.core.recording.reader import read_session
    from hil.core.recording.replay import advertise, replay
    from hil.errors import UsageError

    if args.live is None:
        raise UsageError("replay needs --live [HOST:]PORT (where to serve the session)")
    data = read_session(args.session)
    if not data.messages:
        raise UsageError(f"{args.session}: no readable message to replay")
    if data.recovered:
        print(f"hil: {args.session}: damaged or unfinished; replaying the "
              f"{sum(data.topic_counts.values())} readable messages", file=sys.stderr)
    host, port = parse_address(live_address(args) or "")
    sink = LiveSink(host, port, rates=dict(args.live_rate))
    announce(sink.url, sink.exposure)
    try:
        advertise(data, sink)
        if args.wait is not None and not sink.wait_for_subscriber(args.wait):
            print(f"hil: no client subscribed within {args.wait:g} s; replaying anyway",
                  file=sys.stderr)
        stats = replay(data, sink, args.speed)
        time.sleep(LINGER_S)
    finally:
        sink.close()
    live = sink.stats()
    print(f"hil: replayed {stats.messages} messages ({stats.session_s:.2f} s of session) in "
          f"{stats.wall_s:.2f} s; served {sum(live.sent.values())}, decimated "
          f"{sum(live.decimated.values())}", file=sys.stderr)
    return 0
