// The tune page in headless Chromium, driven by playwright-core: the tool
// runs on fixtures/press; the page must show the four rows and the
// contacts and update them; a threshold moved on the page must change the
// server's thresholds and the patch count; a saved calibration must load
// back. Plain HTTP checks of the server's refusals come first.
//
//   TUNE_BIN=target/debug/examples/tune PLAYWRIGHT_DIR=DIR/node_modules \
//     node tests/browser/tune.cjs
//
// Environment: TUNE_BIN (the tool), PLAYWRIGHT_DIR (where playwright-core
// is installed), CHROMIUM (default /usr/bin/chromium), TUNE_SCREENSHOT (a
// PNG path: a screenshot of the page), TUNE_FIXTURE (default
// fixtures/press). Prints one line per check and `N passed, M failed`;
// exits 1 on a failure. Speed is not checked (a debug build is slow).
"use strict";

const { spawn } = require("node:child_process");
const fs = require("node:fs");
const net = require("node:net");
const os = require("node:os");
const path = require("node:path");

const root = path.resolve(__dirname, "..", "..");
const bin = process.env.TUNE_BIN || path.join(root, "target/debug/examples/tune");
const pwDir = process.env.PLAYWRIGHT_DIR || path.join(root, "target/tune-browser/node_modules");
const { chromium } = require(path.join(pwDir, "playwright-core"));
const chromiumPath = process.env.CHROMIUM || "/usr/bin/chromium";
const fixture = process.env.TUNE_FIXTURE || path.join(root, "fixtures/press");
// A debug build processes about one frame a second: generous bounds.
const FRAME_WAIT_MS = 120_000;

let passed = 0;
let failed = 0;
function check(name, ok, detail) {
  if (ok) {
    passed += 1;
    console.log(`ok    ${name}`);
  } else {
    failed += 1;
    console.log(`FAIL  ${name}${detail === undefined ? "" : `: ${detail}`}`);
  }
  return ok;
}

const children = [];
// Starts the tool; resolves with its address once it serves.
function startTool(args) {
  return new Promise((resolve, reject) => {
    const child = spawn(bin, [...args, "--port", "0", "--run-for", "900"], {
      stdio: ["ignore", "pipe", "pipe"],
    });
    children.push(child);
    let out = "";
    let err = "";
    const timer = setTimeout(() => reject(new Error(`no address after 60 s: ${out} ${err}`)), 60_000);
    child.stdout.on("data", (d) => {
      out += d;
      const m = out.match(/serving (http:\/\/\S+)/);
      if (m) {
        clearTimeout(timer);
        resolve({ child, url: m[1] });
      }
    });
    child.stderr.on("data", (d) => { err += d; });
    child.on("exit", (code) => {
      clearTimeout(timer);
      reject(new Error(`the tool exited (${code}): ${out} ${err}`));
    });
  });
}

async function state(url, after) {
  const r = await fetch(`${url}state${after === undefined ? "" : `?after=${after}`}`);
  return r.json();
}

// Polls `fn` until it returns a truthy value or `ms` pass; returns that value.
async function until(fn, ms, every = 200) {
  const end = Date.now() + ms;
  for (;;) {
    const v = await fn();
    if (v) return v;
    if (Date.now() > end) return v;
    await new Promise((r) => setTimeout(r, every));
  }
}

// Sends raw bytes, returns the status code the server answered.
function rawStatus(url, bytes) {
  const u = new URL(url);
  return new Promise((resolve) => {
    const s = net.connect(Number(u.port), u.hostname);
    let data = "";
    s.setTimeout(10_000, () => s.destroy());
    s.on("connect", () => s.write(bytes));
    s.on("data", (d) => { data += d; });
    s.on("error", () => {});
    s.on("close", () => {
      const m = data.match(/^HTTP\/1\.1 (\d{3})/);
      resolve(m ? Number(m[1]) : 0);
    });
  });
}

async function post(url, p, body, type = "application/json") {
  const r = await fetch(new URL(p, url), { method: "POST", body, headers: { "Content-Type": type } });
  return r.status;
}

async function httpChecks(url, saveDir) {
  const cases = [
    ["bad JSON", "/control", "{bad", 400],
    ["not an object", "/control", "[1,2]", 400],
    ["unknown control", "/control", '{"volume": 11}', 400],
    ["magnitude out of range", "/control", '{"magnitude": 1000}', 400],
    ["negative sum", "/control", '{"sum": -5}', 400],
    ["kernel 0", "/control", '{"erode": 0}', 400],
    ["kernel 256", "/control", '{"dilate": 256}', 400],
    ["fractional kernel", "/control", '{"dilate": 2.5}', 400],
    ["wrong type", "/control", '{"split": "yes"}', 400],
    ["unknown flow preset", "/control", '{"flow": "warp"}', 400],
    ["save outside the directory", "/save", '{"name": "../escape.json"}', 400],
    ["save an absolute path", "/save", '{"name": "/tmp/abs.json"}', 400],
    ["save without .json", "/save", '{"name": "x.txt"}', 400],
  ];
  for (const [name, p, body, want] of cases) {
    const got = await post(url, p, body);
    check(`HTTP ${name} -> ${want}`, got === want, `got ${got}`);
  }
  const form = await post(url, "/control", '{"magnitude": 0.3}', "text/plain");
  check("HTTP plain-text control (another site's form) -> 415", form === 415, `got ${form}`);
  const u = new URL(url);
  const rebound = await rawStatus(url,
    "POST /control HTTP/1.1\r\nHost: evil.example:8000\r\nContent-Type: application/json\r\n" +
    'Content-Length: 18\r\nConnection: close\r\n\r\n{"magnitude": 0.3}');
  check("HTTP another host name (DNS rebinding) -> 421", rebound === 421, `got ${rebound}`);
  const huge = await rawStatus(url,
    `POST /control HTTP/1.1\r\nHost: ${u.host}\r\nContent-Length: 1000000000000\r\n\r\n{`);
  check("HTTP huge declared body -> 413", huge === 413, `got ${huge}`);
  const big = await post(url, "/control", JSON.stringify({ magnitude: 0.3, pad: "x".repeat(70_000) }));
  check("HTTP 70 kB body -> 413", big === 413, `got ${big}`);
  const garbage = await rawStatus(url, "\u0000\u0001 nonsense\r\n\r\n");
  check("HTTP garbage request -> 400", garbage === 400, `got ${garbage}`);
  const nf = (await fetch(`${url}nope`)).status;
  check("HTTP unknown page -> 404", nf === 404, `got ${nf}`);
  const wrong = (await fetch(`${url}control`)).status;
  check("HTTP GET /control -> 405", wrong === 405, `got ${wrong}`);
  const s = await state(url);
  check("the server answers after the refusals, settings unchanged",
    s.settings && s.settings.magnitude === 0.2 && s.settings.sum === 600, JSON.stringify(s.settings));
  check("nothing was written to the save directory", fs.readdirSync(saveDir).length === 0,
    fs.readdirSync(saveDir).join(" "));
}

async function browserChecks(url, saveDir) {
  const userDir = fs.mkdtempSync(path.join(os.tmpdir(), "tune-chromium-"));
  // A fresh profile (playwright passes it as --user-data-dir).
  const browser = await chromium.launchPersistentContext(userDir, {
    executablePath: chromiumPath,
    headless: true,
    viewport: { width: 1500, height: 1000 },
    args: [
      "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
      "--disable-background-networking", "--disable-component-update", "--disable-sync",
    ],
  });
  try {
    const page = browser.pages()[0] || await browser.newPage();
    const errors = [];
    page.on("pageerror", (e) => errors.push(String(e)));
    await page.goto(url);

    // The four rows: the panel is 1600 x (4 x 200 + 3 gaps of 4 px).
    await page.waitForFunction(() => document.getElementById("panel").naturalWidth > 0,
      null, { timeout: FRAME_WAIT_MS });
    const size = await page.$eval("#panel", (i) => [i.naturalWidth, i.naturalHeight]);
    check("the page shows the four rows (1600 x 812 panel)", size[0] === 1600 && size[1] === 812,
      size.join("x"));
    const labels = await page.$$eval("#row-labels li", (l) => l.length);
    check("the four rows are labelled", labels === 4, labels);

    // They update: the panel's frame number moves on, twice.
    const seq0 = Number(await page.$eval("#panel", (i) => i.dataset.seq));
    const moved = await page.waitForFunction((s) => Number(document.getElementById("panel").dataset.seq) > s + 1,
      seq0, { timeout: FRAME_WAIT_MS }).then(() => true, () => false);
    check("the panel updates with new frames", moved);

    // The contacts: rows with a location and a force.
    const rows = await page.waitForFunction(
      () => document.querySelectorAll("#contacts tr.contact").length > 0,
      null, { timeout: FRAME_WAIT_MS }).then(() => true, () => false);
    check("contacts appear in the table", rows);
    const cells = await page.$$eval("#contacts tr.contact:first-child td", (t) => t.map((c) => c.textContent));
    check("a contact has an id, location (mm), force (N) and the Fz sigma (N)",
      cells.length === 9 && cells.slice(1, 8).every((c) => /^-?\d+\.\d+$/.test(c)), cells.join(" | "));
    // The loop's first frame is the reference itself (no patch): wait for a press.
    const patches = await until(async () => Number(await page.textContent("#patches")), FRAME_WAIT_MS);
    check("the patch count is shown", patches > 0, patches);
    const timing = await page.$$eval("#timing-row td", (t) => t.map((c) => c.textContent));
    check("the time per stage is shown", timing.length === 8 && /^\d+\.\d$/.test(timing[1]), timing.join(" "));

    // A threshold moved on the page: the server's thresholds and the patch count change.
    await page.fill("#magnitude", "5");
    await page.press("#magnitude", "Tab");
    const s1 = await until(async () => {
      const s = await state(url);
      return s.settings.magnitude === 5 ? s : null;
    }, 10_000);
    check("moving the magnitude control sets the server's threshold", s1 !== null);
    const changedAt = s1 ? s1.seq : 0;
    const after = await until(async () => {
      const s = await state(url, changedAt);
      return s.seq > changedAt + 1 ? s : null;
    }, FRAME_WAIT_MS);
    check("with magnitude 5 px the next frames have no patch",
      after !== null && after.frame.patches === 0, after && after.frame.patches);
    const shown = await until(async () => (await page.textContent("#patches")) === "0", 20_000);
    check("the page shows the new patch count", shown);
    const cmd = await page.textContent("#cmdline");
    check("the command line shows the threshold", cmd.includes("--magnitude 5 "), cmd);

    // A preset, then the values to save.
    await page.click("#presets button[data-preset=mid]");
    const mid = await until(async () => (await state(url)).settings.preset === "mid", 10_000);
    check("the mid preset button sets the mid thresholds", mid);
    check("the command line says --thresholds mid",
      await until(async () => (await page.textContent("#cmdline")).includes("--thresholds mid"), 10_000));
    await page.fill("#magnitude", "0.25");
    await page.press("#magnitude", "Tab");
    await page.fill("#sum", "700");
    await page.press("#sum", "Tab");
    const tuned = await until(async () => {
      const s = (await state(url)).settings;
      return s.magnitude === 0.25 && s.sum === 700 ? s : null;
    }, 10_000);
    check("magnitude 0.25 and sum 700 set from the page", tuned !== null, JSON.stringify(tuned));
    const snippet = await until(async () => {
      const t = await page.textContent("#snippet");
      return t.includes('"magnitude": 0.25') && t.includes('"sum": 700.0') ? t : null;
    }, 10_000);
    check("the calibration snippet shows them", snippet !== null);

    // Pause and step.
    await page.click("#pause");
    await until(async () => (await state(url)).paused, 5_000);
    const p0 = await until(async () => {
      // Let a frame in flight land.
      const a = (await state(url)).seq;
      await new Promise((r) => setTimeout(r, 2500));
      const b = (await state(url)).seq;
      return a === b ? b : null;
    }, FRAME_WAIT_MS / 2, 0);
    check("pause stops the frames", p0 !== null);
    await page.click("#step");
    const stepped = await until(async () => (await state(url, p0)).seq === p0 + 1, FRAME_WAIT_MS);
    check("step processes one frame", stepped);
    await page.click("#pause");
    check("play goes on", await until(async () => !(await state(url)).paused, 5_000));

    // Save, then refuse to save over it.
    await page.fill("#save-name", "tuned.json");
    await page.click("#save");
    await page.waitForSelector("#save-result.ok, #save-result.fail", { timeout: 10_000 });
    const saved = await page.textContent("#save-result");
    check("saving writes a new calibration", fs.existsSync(path.join(saveDir, "tuned.json")), saved);
    await page.click("#save");
    const refused = await until(async () => {
      const cls = await page.getAttribute("#save-result", "class");
      const t = await page.textContent("#save-result");
      return cls === "fail" && t.includes("exists") ? t : null;
    }, 10_000);
    check("saving over an existing file is refused", refused !== null);

    if (process.env.TUNE_SCREENSHOT) {
      await page.screenshot({ path: process.env.TUNE_SCREENSHOT, fullPage: true });
      console.log(`wrote ${process.env.TUNE_SCREENSHOT}`);
    }

    // A reload, and a second page after the first closed.
    await page.reload();
    const again = await page.waitForFunction(() => Number(document.getElementById("panel").dataset.seq) > 0,
      null, { timeout: FRAME_WAIT_MS }).then(() => true, () => false);
    check("the page works after a reload", again);
    await page.close();
    const page2 = await browser.newPage();
    const fresh = await page2.goto(url).then(() => page2.waitForFunction(
      () => Number(document.getElementById("panel").dataset.seq) > 0, null, { timeout: FRAME_WAIT_MS }))
      .then(() => true, () => false);
    check("a new page works after one disconnected", fresh);
    // Thresholds estimated from the next 100 frames, taken as rest frames
    // (here they hold presses: the estimate must rise above the tuned 0.25 px).
    await page2.click("#rest");
    const rest = await until(async () => {
      const s = await state(url);
      return s.rest.state === "done" || s.rest.state === "failed" ? s : null;
    }, 4 * FRAME_WAIT_MS, 500);
    check("thresholds estimated from rest frames are applied",
      rest !== null && rest.rest.state === "done" && rest.settings.magnitude > 0.25
        && rest.settings.erode === 9 && rest.settings.dilate === 21,
      rest && JSON.stringify([rest.rest, rest.settings]));
    const shownRest = await until(async () => (await page2.textContent("#rest-state")).includes("rest frames"), 10_000);
    check("the page says what the estimate set", shownRest);
    check("no script error on the page", errors.length === 0, errors.join("; "));
  } finally {
    await browser.close();
    fs.rmSync(userDir, { recursive: true, force: true });
  }
}

async function loadBack(saveDir) {
  const other = fs.mkdtempSync(path.join(os.tmpdir(), "tune-save2-"));
  const { child, url } = await startTool([fixture, "--calibration", path.join(saveDir, "tuned.json"),
    "--save-dir", other]);
  const s = await state(url);
  const t = s.settings;
  check("the saved calibration loads back with the tuned thresholds",
    t.magnitude === 0.25 && t.sum === 700 && t.erode === 9 && t.dilate === 21, JSON.stringify(t));
  const f = await until(async () => (await state(url, 0)).frame, FRAME_WAIT_MS);
  check("and runs", f !== null && f !== undefined);
  child.kill();
  fs.rmSync(other, { recursive: true, force: true });
}

async function main() {
  const saveDir = fs.mkdtempSync(path.join(os.tmpdir(), "tune-save-"));
  try {
    const { url } = await startTool([fixture, "--save-dir", saveDir]);
    console.log(`tool at ${url}`);
    await httpChecks(url, saveDir);
    await browserChecks(url, saveDir);
    await loadBack(saveDir);
  } catch (e) {
    check("the run completes", false, e && e.stack ? e.stack : String(e));
  } finally {
    for (const c of children) c.kill();
    fs.rmSync(saveDir, { recursive: true, force: true });
  }
  console.log(`${passed} passed, ${failed} failed`);
  process.exit(failed === 0 && passed > 0 ? 0 : 1);
}

main();
