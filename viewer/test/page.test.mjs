// The page on a small fixture avatar (fixture.mjs): it loads with no page or console error,
// draws at the view's exact size, a posed frame differs from the T-pose where the arm moved,
// and a missing or truncated data file gives one clear message instead of a blank canvas.
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { mkdtempSync, rmSync, truncateSync, statSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { execFileSync } from 'node:child_process';
import { writeFixture, VIEWER_DIR } from './fixture.mjs';
import { serve } from './serve.mjs';
import { browserSkip, launch, openPage } from './browser.mjs';
import { decodePng, changedFraction } from './png.mjs';

const skip = browserSkip();
let browser;
const dirs = [];

function fixture(mutate) {
  const dir = mkdtempSync(join(tmpdir(), 'lifegom-viewer-'));
  dirs.push(dir);
  writeFixture(dir);
  mutate?.(dir);
  return dir;
}

before(async () => {
  if (!skip) browser = await launch();
});
after(async () => {
  await browser?.close();
  for (const d of dirs) rmSync(d, { recursive: true, force: true });
});

test('vendored scripts are the pinned packages', () => {
  execFileSync(process.execPath, [join(VIEWER_DIR, 'tools/vendor.mjs'), '--check'], { stdio: 'inherit' });
});

test('draws the fixture, and the arm moves', { skip }, async () => {
  const server = await serve(fixture());
  try {
    const { page, errors, ok } = await openPage(browser, server.url);
    assert.ok(ok, await page.textContent('#error'));
    const size = await page.evaluate(() => {
      const c = document.querySelector('canvas');
      return [c.width, c.height, c.clientWidth, c.clientHeight, window.devicePixelRatio];
    });
    assert.deepEqual(size, [256, 256, 256, 256, 1]);
    await page.evaluate(() => window.lifegom.show({ view: 0, motion: 'tpose', time: 0 }));
    const rest = decodePng(await page.locator('canvas').screenshot());
    await page.evaluate(() => window.lifegom.show({ view: 0, motion: 'swing', time: 1 }));
    const posed = decodePng(await page.locator('canvas').screenshot());
    assert.equal(rest.width, 256);
    // Not blank: the torso covers a good part of the frame.
    let covered = 0;
    for (let i = 0; i < rest.rgb.length; i += 3) if (rest.rgb[i] < 0.9) covered++;
    assert.ok(covered > 0.05 * 256 * 256, `only ${covered} pixels drawn`);
    const moved = changedFraction(rest, posed);
    assert.ok(moved > 0.005, `the swing frame differs from the T-pose in only ${(100 * moved).toFixed(2)} % of the pixels`);
    // The torso (left half) does not move.
    const half = (img) => ({ width: 100, height: 256, rgb: Float64Array.from({ length: 100 * 256 * 3 }, (_, i) => img.rgb[3 * (Math.floor(i / 300) * 256) + (i % 300)]) });
    assert.ok(changedFraction(half(rest), half(posed)) < 0.002, 'the torso moved');
    assert.deepEqual(errors, []);
  } finally {
    server.close();
  }
});

for (const [what, mutate, expect] of [
  ['a missing data file', (d) => rmSync(join(d, 'avatar.bin')), /avatar\.bin: missing/],
  ['a truncated data file', (d) => truncateSync(join(d, 'avatar.bin'), statSync(join(d, 'avatar.bin')).size - 100), /avatar\.bin: \d+ bytes, avatar\.json says \d+ \(truncated\)/],
  ['a truncated motion', (d) => truncateSync(join(d, 'motion_swing.bin'), 10), /motion_swing\.bin: 10 bytes/],
  ['a missing manifest', (d) => rmSync(join(d, 'avatar.json')), /avatar\.json: missing/],
  ['a manifest without a field', (d) => writeFileSync(join(d, 'avatar.json'), '{"format": "lifegom-viewer", "version": 1, "files": {}}'), /avatar\.json: field `arrays`/],
]) {
  test(`${what} shows one clear message`, { skip }, async () => {
    const server = await serve(fixture(mutate));
    try {
      const { page, ok } = await openPage(browser, server.url);
      assert.equal(ok, false);
      const message = await page.textContent('#error');
      assert.match(message, expect);
      assert.equal(await page.isVisible('#error'), true);
      assert.equal(await page.isVisible('canvas'), false);
    } finally {
      server.close();
    }
  });
}
