"""Relabelling a closed MCAP log: its `fuelid` metadata record updated, e.g. with the truck's VIN when the
file was closed before the VIN was first seen (and so names the truck by its placeholder, which the fleet
server refuses for the VIN's token)."""
from __future__ import annotations

import os
from pathlib import Path

from mcap.reader import SeekingReader
from mcap.writer import CompressionType, Writer

from fuelid import __version__
from fuelid.logger.durable import fsync_path
from fuelid.logger.mcap_log import METADATA_NAME


def relabel(path: str | Path, metadata: dict[str, str]) -> None:
    """Rewrite the complete MCAP file `path` with `metadata` merged into its `fuelid` record, in place and
    atomically (a power cut leaves the old file or the new one). Schemas, channels, messages (their bytes,
    times and sequence numbers), attachments and the other metadata records are copied; chunk CRCs are checked
    on the way, so a damaged file raises (mcap's error) and stays as it was."""
    path = Path(path)
    tmp = path.with_name(path.name + ".relabel")
    try:
        with open(path, "rb") as f, open(tmp, "wb") as out:
            reader = SeekingReader(f, validate_crcs=True)
            summary = reader.get_summary()
            writer = Writer(out, compression=CompressionType.ZSTD)
            writer.start(profile=reader.get_header().profile, library=f"fuelid/{__version__} relabel")
            schemas = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()}
            channels = {i: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0),
                                                   c.metadata) for i, c in summary.channels.items()}
            for _, channel, message in reader.iter_messages(log_time_order=False):
                writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
            for a in reader.iter_attachments():  # the message columns: they hold the messages just copied
                writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
            fuelid: dict[str, str] = {}
            for record in reader.iter_metadata():
                writer.add_metadata(record.name, record.metadata)
                fuelid = dict(record.metadata) if record.name == METADATA_NAME else fuelid
            writer.add_metadata(METADATA_NAME, {**fuelid, **metadata})  # the last record of a name wins
            writer.finish()
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    fsync_path(path.parent)
