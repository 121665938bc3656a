// Reads every message of an MCAP file with the TypeScript reference reader (@mcap/core) the way Foxglove's
// McapIterableSource does: the indexed reader when the summary has chunk indexes (and channels), else the
// stream reader. Prints {"reader", "messages", "statistics"} as JSON; exits 1 with {"error"} on failure.
// Usage: NODE_PATH=<dir with @mcap/core and fzstd> node mcap_ts_read.cjs FILE.mcap
const fs = require("fs");
const { McapIndexedReader, McapStreamReader } = require("@mcap/core");
const fzstd = require("fzstd");

const decompressHandlers = { zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))) };

async function main(path) {
  const fd = fs.openSync(path, "r");
  const readable = {
    size: async () => BigInt(fs.fstatSync(fd).size),
    read: async (offset, length) => {
      const buf = new Uint8Array(Number(length));
      fs.readSync(fd, buf, 0, buf.length, Number(offset));
      return buf;
    },
  };
  const indexed = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const statistics = Number(indexed.statistics?.messageCount ?? -1n);
  let messages = 0;
  let reader;
  if (indexed.chunkIndexes.length > 0 && indexed.channelsById.size > 0) {
    reader = "indexed";
    for await (const _ of indexed.readMessages()) messages++;
  } else {
    reader = "stream";
    const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
    stream.append(fs.readFileSync(path));
    for (let record; (record = stream.nextRecord()); ) if (record.type === "Message") messages++;
    if (!stream.done()) throw new Error("stream reader stopped before the end of the file");
  }
  console.log(JSON.stringify({ reader, messages, statistics }));
}

main(process.argv[2]).catch((err) => {
  console.log(JSON.stringify({ error: String(err && err.message ? err.message : err) }));
  process.exit(1);
});
