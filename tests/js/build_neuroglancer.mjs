// Bundles neuroglancer (npm: ES modules, no built site) into a static viewer with esbuild:
//   node tests/js/build_neuroglancer.mjs [OUT_DIR]     (default tests/js/neuroglancer)
// writes OUT_DIR/index.html, main.bundle.{js,css}, chunk_worker.bundle.js and
// async_computation.bundle.js, side by side, to be served from one folder
// (scripts/serve_ome_zarr.py --neuroglancer OUT_DIR). Run by scripts/fetch-js-deps.sh after npm ci; used by
// tests/python/test_ome_zarr_browser.py. The three entry points are neuroglancer's own
// (lib/*.bundle.js); its package.json "imports" pick the data sources: zarr (v2 and v3, OME-NGFF)
// and precomputed (segment properties) only, the other sources compiled out.
import fs from "node:fs";
import path from "node:path";
import { fileURLToPath } from "node:url";
import * as esbuild from "esbuild";

const here = path.dirname(fileURLToPath(import.meta.url));
const out = path.resolve(process.argv[2] ?? path.join(here, "neuroglancer"));
const lib = path.join(here, "node_modules", "neuroglancer", "lib");
const emptyIcon = '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 24 24"></svg>';

const neuroglancerSources = {
  name: "neuroglancer-sources",
  setup(build) {
    // Icons are imported as text ("ikonate/icons/NAME.svg?raw"). The ikonate on npm (1.1.1,
    // pinned by the overrides in package.json) lacks three icons of the git revision neuroglancer
    // names: those buttons get an empty icon.
    build.onResolve({ filter: /\?raw$/ }, (args) => ({
      path: path.join(here, "node_modules", args.path.slice(0, -"?raw".length)),
      namespace: "raw-text",
    }));
    build.onLoad({ filter: /.*/, namespace: "raw-text" }, (args) => ({
      contents: fs.existsSync(args.path) ? fs.readFileSync(args.path, "utf8") : emptyIcon,
      loader: "text",
    }));
    // The async-computation worker is started from lib/async_computation/request.js as
    // "../async_computation.bundle.js" relative to that module; bundled, import.meta.url is the
    // bundle's own URL, and the worker lies beside it.
    build.onLoad({ filter: /async_computation[\\/]request\.js$/ }, (args) => {
      const text = fs.readFileSync(args.path, "utf8");
      const from = '"../async_computation.bundle.js"';
      if (!text.includes(from)) throw new Error(`${args.path}: no ${from} (neuroglancer changed)`);
      return {
        contents: text.replace(from, '"./async_computation.bundle.js"'),
        loader: "js",
        resolveDir: path.dirname(args.path),
      };
    });
  },
};

fs.rmSync(out, { recursive: true, force: true });
const result = await esbuild.build({
  entryPoints: ["main", "chunk_worker", "async_computation"].map((n) => `${lib}/${n}.bundle.js`),
  bundle: true,
  format: "esm",
  outdir: out,
  minify: true,
  target: "es2022",
  loader: { ".svg": "text", ".wasm": "file", ".png": "file" },
  assetNames: "[name]",
  conditions: [
    "neuroglancer/datasource:none_by_default",
    "neuroglancer/datasource/zarr:enabled",
    "neuroglancer/datasource/precomputed:enabled",
  ],
  plugins: [neuroglancerSources],
  logLevel: "error",
});
if (result.errors.length) process.exit(1);
fs.writeFileSync(
  path.join(out, "index.html"),
  `<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>neuroglancer</title>
<link href="main.bundle.css" rel="stylesheet"></head>
<body><script src="main.bundle.js" type="module"></script></body></html>
`,
);
const files = fs.readdirSync(out);
const bytes = files.reduce((n, f) => n + fs.statSync(path.join(out, f)).size, 0);
console.log(`build_neuroglancer: ${out}: ${files.length} files, ${(bytes / 1e6).toFixed(1)} MB`);
