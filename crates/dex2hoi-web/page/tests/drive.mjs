// Drives the web page in headless Chromium for the browser test
// (crates/dex2hoi-cli/tests/web.rs) and prints what it saw as JSON.
//
//   node drive.mjs SITE_DIR OUT_DIR '{"prompt": ..., "object": ..., "seed": ..., "seconds": ...,
//     "unknownWordsPrompt": ...}'
//
// It serves SITE_DIR on a free localhost port, loads the page, generates the request, keeps
// screenshots in OUT_DIR (the view before and after, the whole page), then submits an empty
// prompt, a broken mesh and a prompt with words the model never saw (one second of motion),
// and reports the page's messages.
import fs from 'node:fs';
import http from 'node:http';
import path from 'node:path';
import { chromium } from 'playwright-core';

const [siteArgument, out, requestJson] = process.argv.slice(2);
const site = path.resolve(siteArgument);
const request = JSON.parse(requestJson);
fs.mkdirSync(out, { recursive: true });

const TYPES = {
  '.html': 'text/html; charset=utf-8',
  '.js': 'text/javascript; charset=utf-8',
  '.css': 'text/css; charset=utf-8',
  '.wasm': 'application/wasm',
};

const server = http.createServer((req, res) => {
  const relative = decodeURIComponent(new URL(req.url, 'http://localhost').pathname);
  const file = path.join(site, relative.endsWith('/') ? `${relative}index.html` : relative);
  if (!file.startsWith(site) || !fs.statSync(file, { throwIfNoEntry: false })?.isFile()) {
    res.writeHead(404).end();
    return;
  }
  const type = TYPES[path.extname(file)] ?? 'application/octet-stream';
  res.writeHead(200, { 'Content-Type': type }).end(fs.readFileSync(file));
});
await new Promise((resolve) => server.listen(0, '127.0.0.1', resolve));
const url = `http://127.0.0.1:${server.address().port}/`;

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium',
  args: [
    '--no-sandbox', '--disable-gpu', '--enable-unsafe-swiftshader', '--disable-quic',
    '--no-first-run', '--disable-background-networking', '--disable-component-update',
    '--disable-sync',
  ],
});
const report = { consoleErrors: [] };
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 860 } });
  page.on('pageerror', (error) => report.consoleErrors.push(String(error)));
  page.on('console', (message) => {
    if (message.type() === 'error') {
      report.consoleErrors.push(message.text());
    }
  });
  const state = () => page.evaluate(() => document.body.dataset.state);
  const settle = (states, timeout) => page.waitForFunction(
    (wanted) => wanted.includes(document.body.dataset.state), states, { timeout },
  );
  // What the page shows after a request that should fail.
  const outcome = async () => ({
    state: await state(),
    message: await page.textContent('#message'),
    playerShown: await page.isVisible('#player'),
    downloadsShown: await page.isVisible('#downloads'),
    result: await page.evaluate(() => window.dex2hoiResult),
  });
  // The canvas's pixels (RGBA), read through a 2D canvas.
  const pixels = () => page.evaluate(() => {
    const canvas = document.getElementById('canvas');
    const copy = new OffscreenCanvas(canvas.width, canvas.height);
    const context = copy.getContext('2d');
    context.drawImage(canvas, 0, 0);
    return Array.from(context.getImageData(0, 0, canvas.width, canvas.height).data);
  });

  const loadStarted = Date.now();
  await page.goto(url);
  await settle(['ready', 'failed'], 120000);
  report.loadSeconds = (Date.now() - loadStarted) / 1000;
  report.loadState = await state();
  report.loadMessage = await page.textContent('#message');
  if (report.loadState !== 'ready') {
    throw new Error(`the page did not get ready: ${report.loadMessage}`);
  }
  await page.waitForTimeout(300);
  const before = await pixels();
  await page.locator('#canvas').screenshot({ path: path.join(out, 'view-empty.png') });

  await page.fill('#prompt', request.prompt);
  await page.selectOption('#object-a', request.object);
  await page.fill('#seed', String(request.seed));
  await page.fill('#seconds', String(request.seconds));
  await page.click('#generate');
  await settle(['done', 'error'], 600000);
  report.generateState = await state();
  report.generateMessage = await page.textContent('#message');
  report.result = await page.evaluate(() => window.dex2hoiResult);
  // Paused a quarter of the way in (where a hand holds the object), for the picture.
  await page.click('#play');
  await page.evaluate(() => {
    const slider = document.getElementById('time');
    slider.value = '0.25';
    slider.dispatchEvent(new Event('input'));
  });
  await page.waitForTimeout(500);
  const after = await pixels();
  let changed = 0;
  for (let i = 0; i < after.length; i += 4) {
    const difference = Math.max(
      Math.abs(after[i] - before[i]),
      Math.abs(after[i + 1] - before[i + 1]),
      Math.abs(after[i + 2] - before[i + 2]),
    );
    if (difference > 40) {
      changed += 1;
    }
  }
  report.changedPixelShare = changed / (after.length / 4);
  report.downloadsShown = await page.isVisible('#downloads');
  await page.locator('#canvas').screenshot({ path: path.join(out, 'view-motion.png') });
  await page.screenshot({ path: path.join(out, 'page.png') });

  await page.fill('#prompt', '   ');
  await page.click('#generate');
  await settle(['done', 'error'], 120000);
  report.emptyPrompt = await outcome();

  await page.fill('#prompt', request.prompt);
  await page.setInputFiles('#mesh', {
    name: 'broken.obj',
    mimeType: 'text/plain',
    buffer: Buffer.from('v 0 0 0\nv 1 0 0\nf 1 2 9\n'),
  });
  await page.click('#generate');
  await settle(['done', 'error'], 120000);
  report.badMesh = await outcome();
  await page.screenshot({ path: path.join(out, 'page-error.png') });

  // Words the model never saw: generated, with the warning.
  await page.setInputFiles('#mesh', []);
  await page.fill('#prompt', request.unknownWordsPrompt);
  await page.fill('#seconds', '1');
  await page.click('#generate');
  await settle(['done', 'error'], 120000);
  report.unknownWords = {
    state: await state(),
    message: await page.textContent('#message'),
    frames: await page.evaluate(() => window.dex2hoiResult?.frames),
  };
} finally {
  await browser.close();
  server.close();
}
process.stdout.write(JSON.stringify(report));
