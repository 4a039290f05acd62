// Bundle the page's sources (src/) with three.js into ../services/controller/web/: index.html
// and assets/ whose names carry a hash of their content (the controller caches them for good).
// Run `npm ci && npm run build` here after changing src/; commit what it writes. NO_MINIFY=1
// keeps the names readable (for a profile in the browser); never commit that build.
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

const common = {
  bundle: true,
  minify: !process.env.NO_MINIFY,
  format: "esm",
  target: ["es2022"],
  entryNames: "[name]-[hash]",
  outdir: assets,
  metafile: true,
  legalComments: "linked",
  logLevel: "info",
};
const names = {};
const named = (result) => {
  for (const [file, meta] of Object.entries(result.metafile.outputs)) {
    if (meta.entryPoint) names[meta.entryPoint.split("/").pop().replace(/\.\w+$/, "")] = basename(file);
  }
};
// The 3D view's worker, with three.js: first, as the page's script names it.
named(await build({ ...common, entryPoints: { "hemisphere-worker": join(here, "src", "hemisphere-worker.js") } }));
named(
  await build({
    ...common,
    entryPoints: { app: join(here, "src", "main.js"), style: join(here, "src", "style.css") },
    define: { __HEMISPHERE_WORKER__: JSON.stringify(`/assets/${names["hemisphere-worker"]}`) },
  }),
);
names.app = names.main;
let html = readFileSync(join(here, "src", "index.html"), "utf8");
html = html.replace("{{app}}", `/assets/${names.app}`).replace("{{style}}", `/assets/${names.style}`);
writeFileSync(join(out, "index.html"), html);
const digest = createHash("sha256").update(html).digest("hex").slice(0, 12);
console.log(`wrote ${join(out, "index.html")} (${digest}) with ${names.app} and ${names.style}`);
