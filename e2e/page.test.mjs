// The page of `gagavatar serve` in a real browser: Debian's Chromium driven by playwright-core
// (no browser download). Runs the CLI built by `cargo test` (or $GAGAVATAR_BIN), on the shipped
// demo model and the public-domain astronaut photo. Screenshots go to e2e/out/.
//
//   cd e2e && npm ci && node --test

import { test, before, after } from "node:test";
import assert from "node:assert/strict";
import { spawn, execFileSync } from "node:child_process";
import { mkdirSync, writeFileSync, mkdtempSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const here = path.dirname(fileURLToPath(import.meta.url));
const repo = path.resolve(here, "..");
const bin = process.env.GAGAVATAR_BIN || path.join(repo, "target", "debug", "gagavatar");
const browserPath = process.env.CHROMIUM || "/usr/bin/chromium";
const astronaut = path.join(repo, "assets", "demo", "astronaut.jpg");
const out = path.join(here, "out");
const scratch = mkdtempSync(path.join(tmpdir(), "gagavatar-e2e-"));
mkdirSync(out, { recursive: true });

let server;
let url;
let browser;

/** A solid grey BMP: an image with no face in it. */
function wallBmp(w, h) {
  const row = Math.ceil((w * 3) / 4) * 4;
  const size = 54 + row * h;
  const b = Buffer.alloc(size);
  b.write("BM", 0);
  b.writeUInt32LE(size, 2);
  b.writeUInt32LE(54, 10);
  b.writeUInt32LE(40, 14);
  b.writeInt32LE(w, 18);
  b.writeInt32LE(h, 22);
  b.writeUInt16LE(1, 26);
  b.writeUInt16LE(24, 28);
  b.writeUInt32LE(row * h, 34);
  b.fill(0x80, 54);
  return b;
}

before(async () => {
  server = spawn(bin, ["serve", "--port", "0"], {
    cwd: repo,
    env: Object.assign({}, process.env, { GAGAVATAR_CACHE: path.join(scratch, "cache") }),
    stdio: ["ignore", "ignore", "pipe"],
  });
  url = await new Promise((resolve, reject) => {
    let log = "";
    const timer = setTimeout(() => reject(new Error("the server did not start:\n" + log)), 60000);
    server.stderr.on("data", (d) => {
      log += d.toString();
      const m = log.match(/on (http:\/\/[^ ]+)/);
      if (m) {
        clearTimeout(timer);
        resolve(m[1]);
      }
    });
    server.on("exit", (code) => reject(new Error("the server exited (" + code + "):\n" + log)));
  });
  browser = await chromium.launch({
    executablePath: browserPath,
    headless: true,
    args: ["--no-sandbox"],
  });
});

after(async () => {
  if (browser) await browser.close();
  if (server) server.kill("SIGINT");
  rmSync(scratch, { recursive: true, force: true });
});

async function renders(page) {
  return parseInt((await page.locator("#frame").getAttribute("data-renders")) || "0", 10);
}

async function frameShot(page) {
  return page.locator("#frame").screenshot();
}

test("a photo becomes an avatar; sliders and dragging change the frame", async () => {
  const page = await browser.newPage({ viewport: { width: 1400, height: 900 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(url);
  await page.locator("#model").filter({ hasText: "model:" }).waitFor();
  await page.locator("#file").setInputFiles(astronaut);
  await page.locator("#avatar-panel").waitFor({ state: "visible", timeout: 120000 });
  await page.waitForFunction(() => document.getElementById("frame").naturalWidth > 0);
  assert.ok(await page.locator("#crop").isVisible(), "the tracked crop is shown");
  assert.match(await page.locator("#status").innerText(), /first frame after/);
  await page.screenshot({ path: path.join(out, "avatar.png"), fullPage: true });

  const before = await frameShot(page);
  const n0 = await renders(page);
  await page.locator('[data-k="jaw"]').evaluate((el) => {
    el.value = "0.5";
    el.dispatchEvent(new Event("input"));
  });
  await page.waitForFunction((n) => parseInt(document.getElementById("frame").dataset.renders, 10) > n, n0);
  await page.waitForTimeout(300);
  const jaw = await frameShot(page);
  assert.notDeepEqual(jaw, before, "moving the jaw slider changed nothing");

  const box = await page.locator("#frame").boundingBox();
  const n1 = await renders(page);
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width / 2 + 90, box.y + box.height / 2 + 10, { steps: 6 });
  await page.mouse.up();
  await page.waitForFunction((n) => parseInt(document.getElementById("frame").dataset.renders, 10) > n, n1);
  await page.waitForTimeout(300);
  assert.notDeepEqual(await frameShot(page), jaw, "dragging did not turn the head");
  await page.screenshot({ path: path.join(out, "avatar_moved.png"), fullPage: true });

  const ply = await page.locator("#ply").getAttribute("href");
  const r = await page.request.get(new URL(ply, url).href);
  assert.equal(r.status(), 200);
  assert.equal((await r.body()).subarray(0, 4).toString(), "ply\n");
  assert.deepEqual(errors, []);
  await page.close();
});

test("a photo without a face gets a clear message", async () => {
  const page = await browser.newPage({ viewport: { width: 1400, height: 900 } });
  await page.goto(url);
  const wall = path.join(scratch, "wall.bmp");
  writeFileSync(wall, wallBmp(200, 160));
  await page.locator("#file").setInputFiles(wall);
  const msg = page.locator("#message");
  await msg.waitFor({ state: "visible", timeout: 60000 });
  assert.match(await msg.innerText(), /no face found in the photo/);
  assert.ok(await page.locator("#avatar-panel").isHidden());
  await page.screenshot({ path: path.join(out, "no_face.png"), fullPage: true });
  await page.close();
});

test("an uploaded video is reenacted and plays beside the driver", async () => {
  const clip = path.join(scratch, "clip.mp4");
  // Six frames of the astronaut through a drifting window.
  execFileSync("ffmpeg", [
    "-loglevel", "error", "-y", "-loop", "1", "-framerate", "10", "-i", astronaut,
    "-vf", "crop=280:280:90+4*n:0,scale=128:128", "-frames:v", "6",
    "-c:v", "libx264", "-pix_fmt", "yuv420p", clip,
  ]);
  const page = await browser.newPage({ viewport: { width: 1400, height: 900 } });
  await page.goto(url);
  await page.locator("#file").setInputFiles(astronaut);
  await page.locator("#video-panel").waitFor({ state: "visible", timeout: 120000 });
  await page.locator("#video-file").setInputFiles(clip);
  await page.locator("#result-download").waitFor({ state: "visible", timeout: 180000 });
  assert.match(await page.locator("#job-status").innerText(), /Done/);
  const dur = await page.locator("#result-video").evaluate(
    (v) => new Promise((ok) => (v.readyState >= 1 ? ok(v.duration) : v.addEventListener("loadedmetadata", () => ok(v.duration)))),
  );
  assert.ok(dur > 0.4 && dur < 1.0, "the result lasts " + dur + " s, the driver 0.6 s");
  await page.screenshot({ path: path.join(out, "reenact.png"), fullPage: true });
  await page.close();
});

test("the webcam drives the avatar live (Chromium's fake camera playing a clip)", async () => {
  const y4m = path.join(scratch, "cam.y4m");
  execFileSync("ffmpeg", [
    "-loglevel", "error", "-y", "-loop", "1", "-framerate", "10", "-i", astronaut,
    "-vf", "crop=300:300:80+6*n:0,scale=320:240", "-frames:v", "10", "-pix_fmt", "yuv420p", y4m,
  ]);
  const camBrowser = await chromium.launch({
    executablePath: browserPath,
    headless: true,
    args: [
      "--no-sandbox",
      "--use-fake-ui-for-media-stream",
      "--use-fake-device-for-media-stream",
      "--use-file-for-fake-video-capture=" + y4m,
    ],
  });
  try {
    const page = await camBrowser.newPage({ viewport: { width: 1400, height: 900 } });
    const errors = [];
    page.on("pageerror", (e) => errors.push(e.message));
    await page.goto(url);
    await page.locator("#file").setInputFiles(astronaut);
    await page.locator("#avatar-panel").waitFor({ state: "visible", timeout: 120000 });
    await page.locator("#webcam").click();
    await page.waitForFunction(() => parseInt(document.getElementById("frame").dataset.live || "0", 10) >= 5, null, { timeout: 120000 });
    assert.equal(await page.locator("#live-status").innerText(), "live");
    await page.screenshot({ path: path.join(out, "webcam.png"), fullPage: true });
    await page.locator("#webcam").click();
    assert.ok(await page.locator("#cam").isHidden(), "the camera preview stays after stopping");
    assert.deepEqual(errors, []);
  } finally {
    await camBrowser.close();
  }
});
