// node read_zarr.mjs STORE OUT_DIR ARRAY...: reads each whole Zarr v3 array STORE/ARRAY with
// zarrita (npm, tests/js/package.json; installed by scripts/fetch-js-deps.sh) and writes its
// elements, C order, little-endian, to OUT_DIR/<i>.bin (i: the array's position in the list);
// prints [{"shape", "data_type"}, ...] as JSON on stdout. One process for many arrays (node's
// start-up dominates small reads). Used by tests/python/test_ome_zarr.py to check an NGFF 0.5
// export with a reader vispack did not write.
import { writeFileSync } from "node:fs";
import * as zarr from "zarrita";
import FileSystemStore from "@zarrita/storage/fs";

const [store, outDir, ...paths] = process.argv.slice(2);
if (!store || !outDir || paths.length === 0) {
  console.error("usage: node read_zarr.mjs STORE OUT_DIR ARRAY...");
  process.exit(2);
}
const root = zarr.root(new FileSystemStore(store));
const infos = [];
for (const [i, path] of paths.entries()) {
  const array = await zarr.open.v3(root.resolve(path), { kind: "array" });
  const chunk = await zarr.get(array);
  const data = chunk.data;
  writeFileSync(`${outDir}/${i}.bin`, Buffer.from(data.buffer, data.byteOffset, data.byteLength));
  infos.push({ shape: chunk.shape, data_type: array.dtype });
}
console.log(JSON.stringify(infos));
