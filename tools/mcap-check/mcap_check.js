#!/usr/bin/env node
// Independent MCAP reader for the cdpr tests: parses a file with the TypeScript reference
// implementation (@mcap/core, streaming reader, chunk CRCs validated), decodes every JSON message,
// and prints a JSON summary: message counts per topic, samples per column-block topic, schemas,
// metadata, attachments, chunks, whether the file ends with a valid footer, and the Statistics
// record's counts if present.
// Usage: node --single-threaded mcap_check.js FILE.mcap
// (without --single-threaded, node 20 was seen to hang at exit, its threads in futex waits, about
// one run in 40 on 2 cores; with it, 0 hangs in 200 runs)
"use strict";
const fs = require("fs");
const { McapStreamReader, McapIndexedReader } = require("@mcap/core");
const fzstd = require("fzstd");
const lz4 = require("lz4js");

// With a valid footer, also read through the summary section: the chunk and message indexes.
async function indexedCounts(buf, decompressHandlers) {
  const readable = {
    size: async () => BigInt(buf.length),
    read: async (offset, length) => buf.subarray(Number(offset), Number(offset + length)),
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const topics = {};
  for await (const msg of reader.readMessages()) {
    const ch = reader.channelsById.get(msg.channelId);
    const topic = ch ? ch.topic : `#${msg.channelId}`;
    topics[topic] = (topics[topic] || 0) + 1;
  }
  return { topics, chunk_indexes: reader.chunkIndexes.length };
}

// A column block (docs/recording.md, "Column blocks"): base64 of the columns one after the other,
// little-endian int64 ("<i8"), float64 ("<f8"), int32 ("<i4") or uint8 ("|u1"); count its samples, check its length and that its
// t_ns column (first) rises and ends at the message's timestamp.
const ITEMSIZE = { "<i8": 8, "<f8": 8, "|u1": 1, "<i4": 4 };
function countBlock(out, topic, body) {
  const raw = Buffer.from(body.data, "base64");
  let size = 0;
  for (const dt of body.dtypes) {
    if (!(dt in ITEMSIZE)) throw new Error(`block dtype ${dt}`);
    size += ITEMSIZE[dt] * body.count;
  }
  if (size !== raw.length || body.columns[0] !== "t_ns") {
    out.bad_blocks += 1;
    return;
  }
  const dv = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
  let prev = null;
  for (let i = 0; i < body.count; i++) {
    const t = dv.getBigInt64(8 * i, true);
    if (prev !== null && t < prev) out.bad_blocks += 1;
    prev = t;
  }
  // an indexed column (body.values[name]: its table): every index within its table
  let pos = 0;
  for (let k = 0; k < body.columns.length; k++) {
    const table = body.values ? body.values[body.columns[k]] : undefined;
    if (table !== undefined) {
      const dt = body.dtypes[k];
      if (!Array.isArray(table) || !["|u1", "<i4", "<i8"].includes(dt)) out.bad_blocks += 1;
      else
        for (let i = 0; i < body.count; i++) {
          const v =
            dt === "|u1"
              ? raw[pos + i]
              : dt === "<i4"
                ? dv.getInt32(pos + 4 * i, true)
                : Number(dv.getBigInt64(pos + 8 * i, true));
          if (v < 0 || v >= table.length) out.bad_blocks += 1;
        }
    }
    pos += ITEMSIZE[body.dtypes[k]] * body.count;
  }
  const last = BigInt(body.timestamp.sec) * 1000000000n + BigInt(body.timestamp.nsec);
  if (prev !== last) out.bad_blocks += 1;
  out.samples[topic] = (out.samples[topic] || 0) + body.count;
}

async function main() {
  const path = process.argv[2];
  if (!path) {
    process.stderr.write("usage: node --single-threaded mcap_check.js FILE.mcap\n");
    process.exit(2);
  }
  const decompressHandlers = {
    zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))),
    lz4: (data, size) => Uint8Array.from(lz4.decompress(data, Number(size))),
  };
  const reader = new McapStreamReader({ decompressHandlers, validateCrcs: true, includeChunks: true });
  const buf = new Uint8Array(fs.readFileSync(path));
  reader.append(buf);
  const channels = new Map();
  const schemas = new Map();
  const out = {
    complete: false,
    topics: {},
    schemas: {},
    metadata: [],
    attachments: [],
    chunks: 0,
    messages: 0,
    bad_json: 0,
    samples: {},
    bad_blocks: 0,
    statistics: null,
    indexed: null,
    error: null,
  };
  const decoder = new TextDecoder();
  try {
    for (let rec; (rec = reader.nextRecord()); ) {
      switch (rec.type) {
        case "Schema":
          schemas.set(rec.id, rec);
          break;
        case "Channel":
          channels.set(rec.id, rec);
          break;
        case "Chunk":
          out.chunks += 1;
          break;
        case "Message": {
          const ch = channels.get(rec.channelId);
          const topic = ch ? ch.topic : `#${rec.channelId}`;
          out.topics[topic] = (out.topics[topic] || 0) + 1;
          out.messages += 1;
          if (ch && ch.messageEncoding === "json") {
            try {
              const body = JSON.parse(decoder.decode(rec.data));
              if (ch.metadata.get("storage") === "column_blocks") countBlock(out, topic, body);
            } catch (e) {
              out.bad_json += 1;
            }
          }
          if (ch && schemas.has(ch.schemaId)) out.schemas[topic] = schemas.get(ch.schemaId).name;
          break;
        }
        case "Metadata":
          out.metadata.push({ name: rec.name, keys: [...rec.metadata.keys()].sort() });
          break;
        case "Attachment":
          out.attachments.push({ name: rec.name, media_type: rec.mediaType, size: rec.data.length });
          break;
        case "Statistics": {
          const perChannel = {};
          for (const [id, n] of rec.channelMessageCounts) {
            const ch = channels.get(id);
            perChannel[ch ? ch.topic : `#${id}`] = Number(n);
          }
          out.statistics = { message_count: Number(rec.messageCount), per_topic: perChannel };
          break;
        }
        default:
          break;
      }
    }
    out.complete = reader.done();
  } catch (e) {
    out.error = String(e && e.message ? e.message : e);
  }
  if (out.complete) {
    try {
      out.indexed = await indexedCounts(buf, decompressHandlers);
    } catch (e) {
      out.error = "indexed reader: " + String(e && e.message ? e.message : e);
    }
  }
  process.stdout.write(JSON.stringify(out) + "\n");
}

main().catch((e) => {
  process.stderr.write(String(e) + "\n");
  process.exit(1);
});
