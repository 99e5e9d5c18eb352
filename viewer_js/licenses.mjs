// Writes ../diff4splat/io/viewer_assets/LICENSES.txt: name, exact version and licence text of every npm package
// bundled into viewer.js (run by `npm run build` after esbuild; the list is esbuild's metafile inputs).
import { readFileSync, writeFileSync } from "node:fs";

const meta = JSON.parse(readFileSync("meta.json", "utf8"));
const pkgs = new Set();
for (const input of Object.keys(meta.inputs)) {
  const m = input.match(/node_modules\/((?:@[^/]+\/)?[^/]+)\//);
  if (m) pkgs.add(m[1]);
}
let out = "Third-party code bundled into diff4splat/io/viewer_assets/viewer.js (built from viewer_js/ by `npm ci && npm run build`).\n";
for (const name of [...pkgs].sort()) {
  const pj = JSON.parse(readFileSync(`node_modules/${name}/package.json`, "utf8"));
  const text = readFileSync(`node_modules/${name}/LICENSE`, "utf8");
  out += `\n${"=".repeat(78)}\n${name} ${pj.version} (${pj.license})\n${"=".repeat(78)}\n${text.trim()}\n`;
}
writeFileSync("../diff4splat/io/viewer_assets/LICENSES.txt", out);
console.log(`LICENSES.txt: ${[...pkgs].sort().join(", ")}`);
