// Bundle the page's sources (src/) with three.js into ../services/controller/web/: index.html
// and assets/ whose names carry a hash of their content (the controller caches them for good).
// Run `npm ci && npm run build` here after changing src/; commit what it writes.
import { build } from "esbuild";
import { createHash } from "node:crypto";
import { mkdirSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { basename, dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "..", "services", "controller", "web");
const assets = join(out, "assets");
rmSync(out, { recursive: true, force: true });
mkdirSync(assets, { recursive: true });

const result = await build({
  entryPoints: { app: join(here, "src", "main.js"), style: join(here, "src", "style.css") },
  bundle: true,
  minify: true,
  format: "esm",
  splitting: true, // three.js in a chunk of its own, loaded after the first paint
  chunkNames: "[name]-[hash]",
  target: ["es2022"],
  entryNames: "[name]-[hash]",
  outdir: assets,
  metafile: true,
  legalComments: "linked",
  logLevel: "info",
});

const names = {};
for (const [file, meta] of Object.entries(result.metafile.outputs)) {
  if (meta.entryPoint?.endsWith("src/main.js")) names.app = basename(file);
  if (meta.entryPoint?.endsWith("src/style.css")) names.style = basename(file);
}
let html = readFileSync(join(here, "src", "index.html"), "utf8");
html = html.replace("{{app}}", `/assets/${names.app}`).replace("{{style}}", `/assets/${names.style}`);
writeFileSync(join(out, "index.html"), html);
const digest = createHash("sha256").update(html).digest("hex").slice(0, 12);
console.log(`wrote ${join(out, "index.html")} (${digest}) with ${names.app} and ${names.style}`);
