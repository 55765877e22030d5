// The tune page: two loops of long polls, one for each new frame's
// findings (GET /state?after=N) and one for the panel (GET
// /frame.png?after=N; the server draws a panel only once the previous one
// was fetched), each answered when there is something newer or after a
// second; controls are sent as JSON (POST /control).
"use strict";

const $ = (id) => document.getElementById(id);
let current = null; // the last state received
let shown = []; // times of the panels shown, for the page's frame rate

function fmt(x, digits) {
  return typeof x === "number" ? x.toFixed(digits) : "-";
}

async function post(path, body) {
  const r = await fetch(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  let value = null;
  try {
    value = await r.json();
  } catch (e) {
    value = { error: "no JSON answer" };
  }
  return { ok: r.ok, status: r.status, value };
}

async function control(body) {
  const r = await post("/control", body);
  $("error").textContent = r.ok ? "" : r.value.error;
  if (r.ok) renderState(r.value);
}

// Sets an input from the server unless the user is editing it.
function setInput(id, value) {
  const el = $(id);
  if (document.activeElement === el) return;
  if (el.type === "checkbox") el.checked = value;
  else if (String(el.value) !== String(value)) el.value = value;
}

function renderState(s) {
  current = s;
  const st = s.settings;
  for (const k of ["magnitude", "sum", "erode", "dilate"]) {
    setInput(k, st[k]);
    setInput(k + "-range", st[k]);
  }
  const flow = $("flow");
  if (flow.options.length === 0) {
    for (const name of s.flow_presets) flow.add(new Option(name, name));
  }
  setInput("flow", st.flow);
  for (const k of ["split", "filter", "rereference"]) setInput(k, st[k]);
  $("filter").disabled = $("rereference").disabled = s.mode !== "calibrated";
  for (const b of document.querySelectorAll("#presets button")) {
    b.classList.toggle("active", b.dataset.preset === st.preset);
  }
  $("initial-preset").textContent = s.mode === "calibrated" ? "calibration's" : "as started";
  $("pause").textContent = s.paused ? "play" : "pause";
  $("mode").textContent = s.mode === "calibrated" ? "calibrated" : "raw (no calibration)";
  $("cmdline").textContent = s.command_line;
  $("snippet").textContent = s.calibration_snippet;
  $("save-dir").textContent = s.save_dir;
  $("save").disabled = !s.can_save;
  $("fps").textContent = fmt(s.fps, 1);
  const rest = s.rest;
  $("rest-state").textContent =
    rest.state === "collecting" ? `collecting ${rest.frames}/${rest.of} frames at rest`
    : rest.state === "idle" ? "" : rest.message;
  if (s.error) $("error").textContent = s.error;
  const f = s.frame;
  if (!f) return;
  $("frame-name").textContent = `frame ${f.frame} (#${s.seq}), t = ${fmt(f.t_s, 3)} s`;
  $("patches").textContent = f.patches;
  $("n-contacts").textContent = f.contacts;
  $("splits").textContent = f.splits;
  $("reref").textContent = f.rereferenced ? "new reference (quiet, small flow)" : "";
  const t = f.timings_ms;
  $("timing-row").innerHTML = [t.crop, t.flow, t.segment, t.hhd, t.contacts, t.process, t.panel, s.encode_ms]
    .map((x) => `<td>${fmt(x, 1)}</td>`).join("");
  renderItems(s.mode, f.items);
}

function renderItems(mode, items) {
  const head = mode === "calibrated"
    ? ["id", "x mm", "y mm", "z mm", "Fx N", "Fy N", "Fz N", "\u03c3 Fz N", "marks"]
    : ["k", "x px", "y px", "box x,y,w,h", "strength", "ds1", "ds2", "dn", "d_pf"];
  const headHtml = "<tr>" + head.map((h) => `<th>${h}</th>`).join("") + "</tr>";
  if ($("contacts-head").innerHTML !== headHtml) $("contacts-head").innerHTML = headHtml;
  const rows = items.map((c, k) => {
    let cells;
    if (mode === "calibrated") {
      const marks = [c.held && "held", c.fallback && "fallback", c.out_of_domain && "out of domain"]
        .filter(Boolean).join(", ");
      // One standard deviation of the Fz error, when the calibration has an uncertainty model.
      const sigma = c.force_sigma_n ? fmt(c.force_sigma_n[2], 3) : "";
      cells = [c.id, ...c.location_mm.map((v) => fmt(v, 2)), ...c.force_n.map((v) => fmt(v, 3)), sigma, marks];
    } else {
      cells = [k, fmt(c.x_px, 1), fmt(c.y_px, 1), c.box_px.join(","), fmt(c.strength, 0),
        fmt(c.ds1, 1), fmt(c.ds2, 1), fmt(c.dn, 1), fmt(c.d_pf, 2)];
    }
    return "<tr class=\"contact\">" + cells.map((v) => `<td>${v}</td>`).join("") + "</tr>";
  });
  $("contacts").innerHTML = rows.join("");
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// The panels: each request waits for a panel newer than the one shown
// (GET /frame.png?after=N), which is decoded off screen, then swapped in.
async function panels() {
  let seq = 0;
  let objectUrl = null;
  for (;;) {
    try {
      const r = await fetch(`/frame.png?after=${seq}`);
      if (r.status !== 200) {
        await sleep(r.status === 204 ? 0 : 500);
        continue;
      }
      const next = Number(r.headers.get("X-Panel-Seq"));
      const url = URL.createObjectURL(await r.blob());
      const img = new Image();
      img.src = url;
      await img.decode();
      const old = $("panel");
      img.id = "panel";
      img.alt = old.alt;
      img.dataset.seq = String(next);
      old.replaceWith(img);
      if (objectUrl) URL.revokeObjectURL(objectUrl);
      objectUrl = url;
      seq = next;
      $("panel-seq").textContent = `panel of #${next}`;
      const now = performance.now();
      shown.push(now);
      shown = shown.filter((t) => now - t < 5000);
      if (shown.length > 1) {
        $("page-fps").textContent = fmt((shown.length - 1) * 1000 / (now - shown[0]), 1);
      }
    } catch (e) {
      await sleep(1000);
    }
  }
}

// The findings: each request waits for a frame newer than the last.
async function poll() {
  let after = 0;
  for (;;) {
    try {
      const r = await fetch(`/state?after=${after}`);
      const s = await r.json();
      renderState(s);
      $("status").textContent = "";
      after = Math.max(after, s.seq);
    } catch (e) {
      $("status").textContent = "server not answering, retrying";
      await sleep(1000);
    }
  }
}

function wire() {
  for (const k of ["magnitude", "sum", "erode", "dilate"]) {
    const send = (el) => {
      const v = Number(el.value);
      if (el.value === "" || !Number.isFinite(v)) return;
      control({ [k]: v });
    };
    $(k).addEventListener("change", () => send($(k)));
    $(k + "-range").addEventListener("input", () => { $(k).value = $(k + "-range").value; });
    $(k + "-range").addEventListener("change", () => send($(k + "-range")));
  }
  for (const b of document.querySelectorAll("#presets button")) {
    b.addEventListener("click", () => control({ preset: b.dataset.preset }));
  }
  $("rest").addEventListener("click", () => control({ rest_estimate: true }));
  $("flow").addEventListener("change", () => control({ flow: $("flow").value }));
  for (const k of ["split", "filter", "rereference"]) {
    $(k).addEventListener("change", () => control({ [k]: $(k).checked }));
  }
  $("pause").addEventListener("click", () => control({ paused: !(current && current.paused) }));
  $("step").addEventListener("click", () => control({ step: true }));
  $("reference").addEventListener("click", () => control({ reference: true }));
  $("save").addEventListener("click", async () => {
    const r = await post("/save", { name: $("save-name").value });
    const el = $("save-result");
    el.className = r.ok ? "ok" : "fail";
    el.textContent = r.ok ? `saved ${r.value.path}` : r.value.error;
  });
}

wire();
poll();
panels();
