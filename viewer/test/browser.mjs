// Starts Debian's chromium through playwright-core (no browser download), software WebGL
// through SwiftShader, device pixel ratio 1. Without a browser the tests skip, unless
// LIFEGOM_REQUIRE_BROWSER is set (CI), when they fail.
import { existsSync } from 'node:fs';

export const CHROMIUM = process.env.LIFEGOM_CHROMIUM ?? '/usr/bin/chromium';
export const REQUIRED = Boolean(process.env.LIFEGOM_REQUIRE_BROWSER);

export function browserSkip() {
  if (existsSync(CHROMIUM)) return false;
  const why = `no browser at ${CHROMIUM} (apt-get install chromium, or set LIFEGOM_CHROMIUM)`;
  if (REQUIRED) throw new Error(`LIFEGOM_REQUIRE_BROWSER is set but there is ${why}`);
  console.warn(`SKIPPED: ${why}`);
  return why;
}

export async function launch() {
  const { chromium } = await import('playwright-core');
  return chromium.launch({
    executablePath: CHROMIUM,
    args: ['--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist'],
  });
}

/** A page that records every page error and console error. */
export async function openPage(browser, url, size = { width: 900, height: 800 }) {
  const page = await browser.newPage({ viewport: size, deviceScaleFactor: 1 });
  const errors = [];
  page.on('pageerror', (e) => errors.push(`page error: ${e.message}`));
  page.on('console', (m) => {
    if (m.type() === 'error') errors.push(`console error: ${m.text()}`);
  });
  await page.goto(url);
  const ok = await page.evaluate(() => window.lifegom.ready);
  return { page, errors, ok };
}
