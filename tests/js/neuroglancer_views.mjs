// Opens neuroglancer links in headless Chromium with software WebGL and records what it shows:
//   node tests/js/neuroglancer_views.mjs OUT_DIR URL...
// For URL number i: OUT_DIR/view-i.png (a screenshot of the page, 800x600) and OUT_DIR/view-i.json
// {url, renderer (the WebGL renderer string), ready_ms, text (the page's visible text: layer
// panels, segment lists), panels (the rendered data panels' rectangles in page pixels), errors
// (page errors and every console message that reports a failure, except missing-file probes)}.
// The screenshot is taken once the viewer reports every visible chunk drawn (viewer.isReady(),
// what neuroglancer's own screenshot tool waits for) and two more frames have been drawn.
// Chromium: Debian's /usr/bin/chromium (or $VISPACK_CHROMIUM), driven by puppeteer-core;
// WebGL 2 from SwiftShader through ANGLE. Exit 0 when every view became ready, 1 otherwise,
// 2 on bad arguments. Used by tests/python/test_ome_zarr_browser.py.
import fs from "node:fs";
import path from "node:path";
import puppeteer from "puppeteer-core";

const [outDir, ...urls] = process.argv.slice(2);
if (!outDir || urls.length === 0) {
  console.error("usage: node neuroglancer_views.mjs OUT_DIR URL...");
  process.exit(2);
}
const chromium = process.env.VISPACK_CHROMIUM || "/usr/bin/chromium";
const readyTimeoutMs = Number(process.env.VISPACK_VIEW_TIMEOUT_MS || 30000);
fs.mkdirSync(outDir, { recursive: true });

const browser = await puppeteer.launch({
  executablePath: chromium,
  headless: true,
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-gpu-sandbox", "--disable-dev-shm-usage", "--window-size=800,600"],
});
let failed = false;
try {
  for (const [i, url] of urls.entries()) {
    const page = await browser.newPage();
    await page.setViewport({ width: 800, height: 600 });
    const errors = [];
    page.on("pageerror", (e) => errors.push(`page error: ${e}`));
    page.on("console", (m) => {
      const text = m.text();
      // A missing .zarray/.zattrs/zarr.json is how a Zarr reader probes the version: not a fault.
      if (/Failed to load resource: .* 404/.test(text)) return;
      if (m.type() === "error" || /error|fail/i.test(text)) {
        errors.push(`console ${m.type()}: ${text}`);
      }
    });
    const start = Date.now();
    const record = { url, renderer: null, ready_ms: null, text: "", panels: [], errors };
    try {
      await page.goto(url, { waitUntil: "load" });
      record.renderer = await page.evaluate(() => {
        const gl = document.createElement("canvas").getContext("webgl2");
        if (!gl) return null;
        const info = gl.getExtension("WEBGL_debug_renderer_info");
        return gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
      });
      await page.waitForFunction(() => window.viewer !== undefined && window.viewer.isReady(),
                                 { timeout: readyTimeoutMs, polling: 100 });
      record.ready_ms = Date.now() - start;
      await page.evaluate(() => new Promise((done) =>
        requestAnimationFrame(() => requestAnimationFrame(done))));
    } catch (e) {
      errors.push(`not ready after ${Date.now() - start} ms: ${e.message}`);
      failed = true;
    }
    record.text = await page.evaluate(() => document.body.innerText);
    record.panels = await page.evaluate(() =>
      [...document.querySelectorAll(".neuroglancer-rendered-data-panel")].map((e) => {
        const r = e.getBoundingClientRect();
        return { x: r.x, y: r.y, width: r.width, height: r.height };
      }));
    await page.screenshot({ path: path.join(outDir, `view-${i}.png`) });
    fs.writeFileSync(path.join(outDir, `view-${i}.json`), JSON.stringify(record, null, 1));
    await page.close();
  }
} finally {
  await browser.close();
}
process.exit(failed ? 1 : 0);
