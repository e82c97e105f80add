// Copies the browser files of the pinned npm packages into vendor/, the only scripts the page
// loads (through its import map). They are committed so that a fresh clone exports a working
// viewer with cargo alone, and the page needs no network; `node tools/vendor.mjs --check`
// (run by the tests) fails when they differ from what package-lock.json pins.
import { readFileSync, writeFileSync, mkdirSync, existsSync } from 'node:fs';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';

const root = join(dirname(fileURLToPath(import.meta.url)), '..');

// [from node_modules, to vendor/]
export const FILES = [
  ['three/build/three.module.min.js', 'three/three.module.min.js'],
  ['three/build/three.core.min.js', 'three/three.core.min.js'],
  ['three/examples/jsm/controls/OrbitControls.js', 'three/addons/controls/OrbitControls.js'],
  ['three/examples/jsm/postprocessing/Pass.js', 'three/addons/postprocessing/Pass.js'],
  ['three/LICENSE', 'three/LICENSE'],
  ['@sparkjsdev/spark/dist/spark.module.min.js', 'spark/spark.module.min.js'],
  ['@sparkjsdev/spark/LICENSE', 'spark/LICENSE'],
];

const check = process.argv.includes('--check');
let stale = [];
for (const [from, to] of FILES) {
  const src = join(root, 'node_modules', from);
  if (!existsSync(src)) {
    console.error(`${src} is missing: run \`npm ci\` in viewer/ first`);
    process.exit(2);
  }
  const bytes = readFileSync(src);
  const dst = join(root, 'vendor', to);
  if (check) {
    if (!existsSync(dst) || !readFileSync(dst).equals(bytes)) stale.push(to);
  } else {
    mkdirSync(dirname(dst), { recursive: true });
    writeFileSync(dst, bytes);
  }
}
if (check && stale.length) {
  console.error(`vendor/ differs from the pinned packages: ${stale.join(', ')} (run \`npm run vendor\`)`);
  process.exit(1);
}
