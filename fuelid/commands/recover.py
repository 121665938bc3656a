"""`fuelid recover BROKEN.mcap [-o FIXED.mcap] [--json]`: rewrite a truncated or damaged MCAP log as a valid one,
keeping every intact chunk and saying what was lost."""
from pathlib import Path

from fuelid.logger.mcap_log import recover
from fuelid.output import print_json


def add_arguments(parser) -> None:
    parser.add_argument("input", type=Path, metavar="BROKEN.mcap", help="MCAP file, possibly truncated")
    parser.add_argument("-o", "--output", type=Path, metavar="FIXED.mcap",
                        help="where to write the recovered file (default: BROKEN.recovered.mcap beside the input)")
    parser.add_argument("--json", action="store_true", help="print what was recovered as JSON")


def run(args) -> int:
    output = args.output or args.input.with_name(f"{args.input.stem}.recovered.mcap")
    stats = recover(args.input, output)
    summary = {"input": str(args.input), "output": str(output), **stats.to_dict()}
    if args.json:
        print_json(summary)
        return 0
    if stats.complete:
        print(f"{args.input} was complete")
    else:
        state = "truncated" if stats.truncated else "damaged"
        print(f"{args.input} was {state}: {stats.bytes_lost} of {stats.bytes_total} bytes lost")
    for d in stats.damaged:
        print(f"  skipped damaged bytes {d.start}-{d.end} ({d.reason})")
    if stats.messages_lost:
        print(f"  {stats.messages_lost} messages lost")
    print(f"wrote {output}: {summary['message_count']} messages, {stats.metadata_records} metadata records")
    for topic, count in sorted(stats.messages.items()):
        print(f"  {topic:<24} {count:>10}")
    return 0
