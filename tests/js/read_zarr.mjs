// node read_zarr.mjs STORE ARRAY OUT: reads the whole Zarr v3 array STORE/ARRAY with zarrita
// (npm, tests/js/package.json; installed by scripts/fetch-js-deps.sh) and writes its elements,
// C order, little-endian, to OUT; prints {"shape", "data_type"} as JSON on stdout. Used by
// tests/python/test_ome_zarr.py to check an NGFF 0.5 export with a reader vispack did not write.
import { writeFileSync } from "node:fs";
import * as zarr from "zarrita";
import FileSystemStore from "@zarrita/storage/fs";

const [store, path, out] = process.argv.slice(2);
if (!store || !path || !out) {
  console.error("usage: node read_zarr.mjs STORE ARRAY OUT");
  process.exit(2);
}
const root = zarr.root(new FileSystemStore(store));
const array = await zarr.open.v3(root.resolve(path), { kind: "array" });
const chunk = await zarr.get(array);
const data = chunk.data;
writeFileSync(out, Buffer.from(data.buffer, data.byteOffset, data.byteLength));
console.log(JSON.stringify({ shape: chunk.shape, data_type: array.dtype }));
