// Screenshot of the rerun web viewer in headless Debian chromium, for the README (a developer tool, not installed).
// The viewer's WebAssembly needs real seconds to load and draw, which --screenshot's virtual time does not give it,
// so this drives chromium through the DevTools protocol (loopback only) and waits in real time.
//
// usage: node --experimental-websocket docs/images/screenshot.mjs URL OUT.png [WAIT_S=40] [WIDTHxHEIGHT=1600x1000]
// URL is the web viewer address that `vio run --serve` logs (or `rerun --serve-web --bind 127.0.0.1 FILE.rrd`).
// A live shot: `vio run --serve` outpaces the viewer's loading, so pause vio at the wanted moment (kill -STOP, by
// its pid) while this waits, and kill -CONT it after the shot; the viewer process keeps serving what it received.
import { spawn } from "node:child_process";
import { mkdtempSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";

const [url, out, waitS = "40", size = "1600x1000"] = process.argv.slice(2);
if (!url || !out) {
  console.error("usage: screenshot.mjs URL OUT.png [WAIT_S] [WIDTHxHEIGHT]");
  process.exit(2);
}
const [width, height] = size.split("x").map(Number);
const port = 9300 + Math.floor(Math.random() * 500);
const profile = mkdtempSync(join(tmpdir(), "vio-chromium-"));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

const chrome = spawn("chromium", [
  "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-quic",
  "--no-first-run", "--disable-component-update", "--disable-sync", "--use-angle=swiftshader",
  "--enable-unsafe-swiftshader", `--user-data-dir=${profile}`, `--window-size=${width},${height}`,
  "--remote-debugging-address=127.0.0.1", `--remote-debugging-port=${port}`, "about:blank",
], { stdio: "ignore" });

let target;
for (let i = 0; i < 100 && !target; i++) {
  await sleep(200);
  try {
    const list = await (await fetch(`http://127.0.0.1:${port}/json/list`)).json();
    target = list.find((t) => t.type === "page");
  } catch { /* not up yet */ }
}
if (!target) throw new Error("chromium did not start");

const ws = new WebSocket(target.webSocketDebuggerUrl);
await new Promise((r) => ws.addEventListener("open", r, { once: true }));
let nextId = 1;
const pending = new Map();
ws.addEventListener("message", (ev) => {
  const msg = JSON.parse(ev.data);
  if (msg.id && pending.has(msg.id)) { pending.get(msg.id)(msg); pending.delete(msg.id); }
});
const send = (method, params = {}) => new Promise((resolve) => {
  const id = nextId++;
  pending.set(id, resolve);
  ws.send(JSON.stringify({ id, method, params }));
});

await send("Emulation.setDeviceMetricsOverride", { width, height, deviceScaleFactor: 1, mobile: false });
await send("Page.navigate", { url });
await sleep(Number(waitS) * 1000);
const shot = await send("Page.captureScreenshot", { format: "png" });
writeFileSync(out, Buffer.from(shot.result.data, "base64"));
console.log(`wrote ${out}`);
const exited = new Promise((r) => chrome.once("exit", r));
await send("Browser.close");
ws.close();
await Promise.race([exited, sleep(10000)]);
chrome.kill();
rmSync(profile, { recursive: true, force: true, maxRetries: 5, retryDelay: 500 });
