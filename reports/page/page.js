// dermis interactive comparison page (docs/report-page.md).  Everything it shows comes from
// the manifest and the data blocks at the end of the page (reports/page_data.py);
// nothing here names a model, light, view or geometry.
"use strict";
(function () {
const M = JSON.parse(document.getElementById("manifest").textContent);
const IMAGES = M.images;
const BY_ID = Object.fromEntries(IMAGES.map((e) => [e.id, e]));
const LUM = [0.2126, 0.7152, 0.0722];   // Rec. 709 luminance of linear RGB
const $ = (s) => document.querySelector(s);

function el(tag, attrs, ...kids) {
  const n = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") n.className = v;
    else if (k === "text") n.textContent = v;
    else if (k.startsWith("on")) n.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null) n.setAttribute(k, v);
  }
  for (const k of kids.flat()) if (k !== null && k !== undefined)
    n.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return n;
}
const uniq = (xs) => [...new Set(xs)];
const fmtS = (s) => s == null ? "–" : s < 10 ? s.toFixed(2) + " s" : s < 600 ? s.toFixed(1) + " s"
  : Math.floor(s / 60) + ":" + String(Math.round(s % 60)).padStart(2, "0");
const pct = (x, d = 1) => x == null ? "–" : (100 * x).toFixed(d) + " %";
function p100(x, d) {   // a percentage: d decimals, or two significant digits below 1 %
  const v = 100 * x;
  return Math.abs(v) >= 1 || v === 0 ? v.toFixed(d) : v.toPrecision(2);
}
const pm = (x, s, d = 1) => x == null ? "–" : p100(x, d) + (s == null ? "" : " ± " + p100(s, d)) + " %";
function fmtV(v) {
  if (!isFinite(v)) return String(v);
  if (v === 0) return "0";
  const a = Math.abs(v);
  return a >= 1e4 || a < 1e-3 ? v.toExponential(4) : v.toPrecision(5);
}
const viewName = (v) => v === "main" ? "main camera" : v;
const imgTitle = (e) => `${e.label} · ${e.condition}${e.view !== "main" ? " @ " + e.view : ""}` +
  (e.kind === "model" ? ` · ${e.geometry}` : "");

// ------------------------------------------------------------------ data blocks
// script elements of type application/x-dermis-data, id "d-KEY", holding the base64 of a zlib
// stream, at the end of the document (reports/page_data.py); read when first needed
const cache = {};
const parsed = new Promise((resolve) => {
  if (document.readyState !== "loading") resolve();
  else document.addEventListener("DOMContentLoaded", () => resolve());
});
function loadBytes(key) {
  if (!cache[key]) cache[key] = (async () => {
    let node = document.getElementById("d-" + key);
    if (!node) { await parsed; node = document.getElementById("d-" + key); }
    if (!node) throw new Error("no data block d-" + key);
    const bin = atob(node.textContent);
    const u8 = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) u8[i] = bin.charCodeAt(i);
    const stream = new Blob([u8]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  })();
  return cache[key];
}
const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) {
  const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 31, f = h & 1023;
  HALF[h] = e === 0 ? s * f * 2 ** -24 : e === 31 ? (f ? NaN : s * Infinity) : s * (1 + f / 1024) * 2 ** (e - 15);
}
const decoded = {};
function linearOf(e) {   // {w, h, px: Float32Array planar R, G, B}
  if (!decoded[e.id]) decoded[e.id] = loadBytes(e.key).then((b) => {
    const n = e.width * e.height * 3, px = new Float32Array(n);
    for (let i = 0; i < n; i++) px[i] = HALF[b[i] | (b[n + i] << 8)];
    return { w: e.width, h: e.height, px };
  });
  return decoded[e.id];
}


// ------------------------------------------------------------------ tone mapping
const SRGB = new Uint8ClampedArray(4097);
for (let i = 0; i <= 4096; i++) {
  const x = i / 4096;
  SRGB[i] = Math.round(255 * (x <= 0.0031308 ? 12.92 * x : 1.055 * x ** (1 / 2.4) - 0.055));
}
const TONE = {
  clip: (x) => x,
  reinhard: (x) => x / (1 + x),
  aces: (x) => (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14),
  log: (x) => x > 0 ? (Math.log2(x) + 12) / 12 : 0,
};
function toneImage(img, gain, tone) {
  const { w, h, px } = img, n = w * h, out = new ImageData(w, h), d = out.data, f = TONE[tone];
  for (let i = 0; i < n; i++) {
    for (let c = 0; c < 3; c++) {
      let v = f(px[c * n + i] * gain);
      v = v > 1 ? 1 : v > 0 ? v : 0;
      d[4 * i + c] = SRGB[(v * 4096 + 0.5) | 0];
    }
    d[4 * i + 3] = 255;
  }
  return out;
}
function toCanvas(imageData) {
  const c = document.createElement("canvas");
  c.width = imageData.width; c.height = imageData.height;
  c.getContext("2d").putImageData(imageData, 0, 0);
  return c;
}

// ------------------------------------------------------------------ state
const S = {
  a: null, b: null, mode: "side", kind: "signed", stops: 0, tone: "clip",
  scale: 1, ox: 0, oy: 0, W: 1, H: 1, fit: true, flipShowB: false, wipe: 0.5,
  srcA: null, srcB: null, diffSrc: null, linA: null, linB: null, labels: null, flipMap: null,
  diffScale: {}, hover: null, region: 0, bin: 1, rawA: null, rawB: null, showRegions: false,
  regionSrc: null,
};
const cvA = $("#cv-a"), cvB = $("#cv-b");

// ------------------------------------------------------------------ images tab
const filt = { view: null, condition: "all", geometry: "all" };
function buildFilters() {
  const box = $("#filters");
  box.textContent = "";
  const views = uniq(IMAGES.map((e) => e.view));
  if (filt.view === null) filt.view = views.includes("main") ? "main" : views[0];
  const conds = uniq(IMAGES.filter((e) => e.view === filt.view).map((e) => e.condition));
  const geoms = uniq(IMAGES.filter((e) => e.kind === "model" && e.view === filt.view).map((e) => e.geometry));
  const group = (title, key, values, all) => el("div", { class: "group" }, el("span", { text: title }),
    (all ? ["all", ...values] : values).map((v) => el("button", {
      class: "chip" + (filt[key] === v ? " on" : ""), "data-filter": key, "data-value": v,
      onclick: () => { filt[key] = v; if (key === "view") { filt.condition = "all"; filt.geometry = "all"; } buildFilters(); buildGrid(); },
    }, key === "view" ? viewName(v) : v)));
  if (views.length > 1) box.append(group("View", "view", views, false));
  box.append(group("Lighting", "condition", conds, true));
  box.append(group("Geometry", "geometry", geoms, true));
}
function cardFacts(e) {
  const rows = [];
  const t = e.seconds == null ? "–" : fmtS(e.seconds) + (e.irradiance_seconds != null ? " + " + fmtS(e.irradiance_seconds) + " irr." : "");
  if (e.kind === "reference") {
    rows.push(`${t}${e.spp ? " · " + Math.round(e.spp) + " spp" : ""}`);
    rows.push(`${e.width}×${e.height} px, path traced`);
  } else {
    rows.push(t);
    if (e.truth) rows.push(`truth ${pm(e.truth.distance, e.truth.stderr)}${e.truth.resolved ? "" : " (n.r.)"}`);
    if (e.baseline) rows.push(`${e.baseline.label} ${pm(e.baseline.rel_rmse, e.baseline.noise)}`);
  }
  return rows.map((r) => el("div", {}, r));
}
function card(e) {
  return el("div", { class: "card" + (e.kind === "reference" ? " ref" : ""), "data-id": e.id,
    title: imgTitle(e), onclick: () => openCompare(e.id, defaultPartner(e).id) },
  el("img", { src: e.thumb, alt: imgTitle(e), loading: "lazy" }),
  el("div", { class: "name", text: e.label }), el("div", { class: "facts" }, cardFacts(e)));
}
function buildGrid() {
  const grid = $("#grid");
  grid.textContent = "";
  const sel = IMAGES.filter((e) => e.view === filt.view && (filt.condition === "all" || e.condition === filt.condition));
  const models = uniq(sel.filter((e) => e.kind === "model").map((e) => e.model));
  const labels = Object.fromEntries(sel.map((e) => [e.model, e.label]));
  for (const cond of uniq(sel.map((e) => e.condition))) {
    const here = sel.filter((e) => e.condition === cond);
    const ref = here.find((e) => e.kind === "reference");
    const geoms = uniq(here.filter((e) => e.kind === "model" && (filt.geometry === "all" || e.geometry === filt.geometry)).map((e) => e.geometry));
    const cols = models.length + (ref ? 1 : 0);
    const m = el("div", { class: "matrix", style: `grid-template-columns: 22px repeat(${cols}, minmax(120px, 200px))` });
    m.append(el("div"));
    for (const mod of models) m.append(el("div", { class: "colhead", text: labels[mod] }));
    if (ref) m.append(el("div", { class: "colhead", text: "reference" }));
    geoms.forEach((g, k) => {
      m.append(el("div", { class: "rowhead", text: g }));
      for (const mod of models) {
        const e = here.find((x) => x.kind === "model" && x.model === mod && x.geometry === g);
        m.append(e ? card(e) : el("div"));
      }
      if (ref) m.append(k === 0 ? card(ref) : el("div"));
    });
    if (!geoms.length && ref) { m.append(el("div")); for (const _ of models) m.append(el("div")); m.append(card(ref)); }
    grid.append(el("div", { class: "light-block" },
      el("h2", {}, cond, el("span", { class: "muted", text: viewName(filt.view) + (ref ? " · with path-traced reference" : "") })), m));
  }
}

// ------------------------------------------------------------------ comparator
function defaultPartner(e) {
  const same = IMAGES.filter((x) => x.id !== e.id && x.light === e.light);
  return same.find((x) => x.kind === "reference")
    || same.find((x) => x.model === M.baseline && x.geometry === e.geometry)
    || same[0] || IMAGES.find((x) => x.id !== e.id) || e;
}
function fillSelect(sel) {
  sel.textContent = "";
  for (const light of uniq(IMAGES.map((e) => e.light))) {
    const og = el("optgroup", { label: light.replace("@", " @ ") });
    for (const e of IMAGES.filter((x) => x.light === light))
      og.append(el("option", { value: e.id, text: e.kind === "reference" ? `${e.label}` : `${e.label} · ${e.geometry}` }));
    sel.append(og);
  }
}
async function openCompare(aId, bId) {
  S.a = BY_ID[aId]; S.b = BY_ID[bId];
  showTab("compare");
  $("#sel-a").value = aId; $("#sel-b").value = bId;
  $("#status").textContent = "loading…";
  const [la, lb] = await Promise.all([linearOf(S.a), linearOf(S.b)]);
  if (S.a.id !== aId || S.b.id !== bId) return;
  S.rawA = la; S.rawB = lb;
  S.W = Math.max(la.w, lb.w); S.H = Math.max(la.h, lb.h);
  S.linA = binned(la, S.bin); S.linB = binned(lb, S.bin);
  const reg = (M.regions.views || {})[S.a.view === S.b.view ? S.a.view : ""];
  S.labels = null;
  if (reg) S.labels = { w: reg.width, h: reg.height, px: await loadBytes(reg.key).catch(() => null) };
  S.regionSrc = S.labels && S.labels.px ? regionCanvas(S.labels) : null;
  const flipOf = (x, y) => x.flip && x.flip.against === y.id ? x.flip : null;
  const fl = flipOf(S.a, S.b) || flipOf(S.b, S.a);
  S.flipMap = fl ? { w: fl.width, h: fl.height, mean: fl.mean, px: await loadBytes(fl.key) } : null;
  $("#diffkind button[data-kind=flip]").disabled = !S.flipMap;
  if (!S.flipMap && S.kind === "flip") setKind("signed");
  $("#status").textContent = "";
  S.diffSrc = null;
  retone();
  if (S.fit) fitView();
  numbers();
  regionTable();
  draw();
  window.dermis.ready = true;
}
function binned(img, b) {   // means over blocks covering b x b common-grid pixels
  const k = Math.max(1, Math.round(b * img.w / S.W));
  if (k === 1) return img;
  const w = Math.floor(img.w / k), h = Math.floor(img.h / k), n = img.w * img.h, m = w * h;
  const px = new Float32Array(3 * m);
  for (let c = 0; c < 3; c++) for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
    let s = 0;
    for (let j = 0; j < k; j++) for (let i = 0; i < k; i++) s += img.px[c * n + (y * k + j) * img.w + x * k + i];
    px[c * m + y * w + x] = s / (k * k);
  }
  return { w, h, px, k };
}
function regionCanvas(lab) {
  const img = new ImageData(lab.w, lab.h), d = img.data, cols = M.regions.colours;
  for (let i = 0; i < lab.w * lab.h; i++) {
    const v = lab.px[i];
    if (v > 0 && v < cols.length) { const c = cols[v]; d[4 * i] = c[0]; d[4 * i + 1] = c[1]; d[4 * i + 2] = c[2]; d[4 * i + 3] = 120; }
  }
  return toCanvas(img);
}
function setBin(b) {
  S.bin = b;
  if (!S.rawA) return;
  S.linA = binned(S.rawA, b); S.linB = binned(S.rawB, b);
  retone(); draw(); if (S.last) readout(S.last.x, S.last.y);
}
function gain(e) { return 2 ** ((M.exposure_stops[e.light] || 0) + S.stops); }
function retone() {
  if (!S.linA) return;
  S.srcA = toCanvas(toneImage(S.linA, gain(S.a), S.tone));
  S.srcB = toCanvas(toneImage(S.linB, gain(S.a), S.tone));   // one exposure: A's light
  S.diffSrc = null;
}
const sample = (img, x, y, W, H) => {   // value index of common-grid pixel (x, y) in img
  const ix = Math.min(img.w - 1, Math.floor(x * img.w / W)), iy = Math.min(img.h - 1, Math.floor(y * img.h / H));
  return iy * img.w + ix;
};
function lumAt(img, i) { const n = img.w * img.h; return LUM[0] * img.px[i] + LUM[1] * img.px[n + i] + LUM[2] * img.px[2 * n + i]; }
function diffValues() {   // Float32Array over the common grid, NaN where not defined
  const { W, H } = S, out = new Float32Array(W * H);
  if (S.kind === "flip") {
    for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) out[y * W + x] = S.flipMap.px[sample(S.flipMap, x, y, W, H)] / 255;
    return out;
  }
  let floor = 0;
  if (S.kind === "relative") {   // 5 % of B's mean luminance over its non-zero pixels
    let s = 0, k = 0;
    for (let i = 0; i < S.linB.w * S.linB.h; i++) { const v = lumAt(S.linB, i); if (v > 0) { s += v; k++; } }
    floor = k ? 0.05 * s / k : 1;
  }
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
    const la = lumAt(S.linA, sample(S.linA, x, y, W, H)), lb = lumAt(S.linB, sample(S.linB, x, y, W, H));
    out[y * W + x] = la === 0 && lb === 0 ? NaN : S.kind === "relative" ? (la - lb) / Math.max(lb, floor) : la - lb;
  }
  return out;
}
function defaultDiffScale(vals) {
  if (S.kind === "flip") return 1;
  if (S.kind === "relative") return 0.5;
  const a = [];
  for (let i = 0; i < vals.length; i += 7) if (isFinite(vals[i])) a.push(Math.abs(vals[i]));
  a.sort((p, q) => p - q);
  const v = a.length ? a[Math.floor(0.99 * (a.length - 1))] : 1;
  return v > 0 ? Number(v.toPrecision(2)) : 1;
}
function buildDiff() {
  const vals = diffValues();
  const key = S.a.id + "|" + S.b.id + "|" + S.kind;
  if (S.diffScale[key] == null) S.diffScale[key] = defaultDiffScale(vals);
  const sc = S.diffScale[key];
  $("#diffscale").value = sc;
  const lut = S.kind === "flip" ? M.luts.magma : M.luts.diverging, n = lut.length;
  const img = new ImageData(S.W, S.H), d = img.data;
  for (let i = 0; i < vals.length; i++) {
    const v = vals[i];
    if (!isFinite(v)) { d[4 * i + 3] = 255; continue; }
    const t = S.kind === "flip" ? v / sc : 0.5 + 0.5 * v / sc;
    const c = lut[Math.max(0, Math.min(n - 1, Math.floor(t * n)))];
    d[4 * i] = c[0]; d[4 * i + 1] = c[1]; d[4 * i + 2] = c[2]; d[4 * i + 3] = 255;
  }
  S.diffSrc = toCanvas(img);
  legend(sc, lut);
}
function legend(sc, lut) {
  const cv = $("#legend-bar"), ctx = cv.getContext("2d");
  for (let i = 0; i < 256; i++) { const c = lut[Math.floor(i * lut.length / 256)]; ctx.fillStyle = `rgb(${c})`; ctx.fillRect(i, 0, 1, 12); }
  const short = (x) => String(Number(x.toPrecision(3)));
  const u = S.kind === "relative" ? (x) => short(100 * x) + " %" : short;
  if (S.kind === "flip") { $("#lg-lo").textContent = "0"; $("#lg-mid").textContent = short(sc / 2); $("#lg-hi").textContent = short(sc); }
  else { $("#lg-lo").textContent = u(-sc); $("#lg-mid").textContent = "0"; $("#lg-hi").textContent = u(sc); }
  $("#legend-note").textContent = S.kind === "signed" ? "luminance A − B, linear radiance (blue: A darker, red: A brighter)"
    : S.kind === "relative" ? "luminance (A − B) / max(B, 5 % of B's mean)"
      : `HDR-FLIP of the model against the reference on the reference's pixels (mean ${S.flipMap.mean.toFixed(3)})`;
  $("#diffscale-unit").textContent = S.kind === "relative" ? "(fraction of B)" : S.kind === "flip" ? "(FLIP, 0 to scale)" : "(radiance)";
}
function sizeCanvas(cv) {
  const r = cv.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
  if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
  return { w: r.width, h: r.height, dpr };
}
function fitView() {
  const r = cvA.getBoundingClientRect();
  S.scale = Math.min(r.width / S.W, r.height / S.H);
  S.ox = (S.W - r.width / S.scale) / 2; S.oy = (S.H - r.height / S.scale) / 2;
  S.fit = true;
}
function drawSrc(ctx, src, dpr) {
  const k = S.scale * dpr, sx = S.W / src.width;
  ctx.setTransform(k * sx, 0, 0, k * sx, -S.ox * k, -S.oy * k);
  ctx.drawImage(src, 0, 0);
}
function drawPanel(cv, which) {
  const { w, h, dpr } = sizeCanvas(cv), ctx = cv.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.imageSmoothingEnabled = false;
  ctx.fillStyle = "#000"; ctx.fillRect(0, 0, cv.width, cv.height);
  if (!S.srcA) return;
  if (which === "diff") { if (!S.diffSrc) buildDiff(); drawSrc(ctx, S.diffSrc, dpr); }
  else if (which === "wipe") {
    drawSrc(ctx, S.srcA, dpr);
    const xw = S.wipe * w * dpr;
    ctx.save(); ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.beginPath(); ctx.rect(xw, 0, cv.width - xw, cv.height); ctx.clip();
    drawSrc(ctx, S.srcB, dpr); ctx.restore();
    ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.fillStyle = "#fff"; ctx.fillRect(xw - dpr, 0, 2 * dpr, cv.height);
    ctx.beginPath(); ctx.arc(xw, cv.height / 2, 7 * dpr, 0, 2 * Math.PI); ctx.fill();
  } else drawSrc(ctx, which === "b" ? S.srcB : S.srcA, dpr);
  if (S.showRegions && S.regionSrc) drawSrc(ctx, S.regionSrc, dpr);
  if (S.hover && S.scale >= 4) {   // the pixel under the cursor, outlined in every panel
    const k = S.scale * dpr;
    ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.strokeStyle = "#ffd34d"; ctx.lineWidth = Math.max(1, dpr);
    ctx.strokeRect((S.hover.x - S.ox) * k + 0.5, (S.hover.y - S.oy) * k + 0.5, k - 1, k - 1);
  }
  void h;
}
function draw() {
  const st = $("#stage");
  st.className = "stage " + (S.mode === "side" ? "side" : "single");
  $("#legend").hidden = S.mode !== "diff";
  $("#diffkind").hidden = S.mode !== "diff";
  $("#diffscale-box").hidden = S.mode !== "diff";
  if (S.mode === "side") { drawPanel(cvA, "a"); drawPanel(cvB, "b"); }
  else drawPanel(cvA, S.mode === "diff" ? "diff" : S.mode === "wipe" ? "wipe" : S.flipShowB ? "b" : "a");
  const tA = $("#tag-a"), tB = $("#tag-b");
  if (!S.a) return;
  tB.textContent = "B · " + imgTitle(S.b);
  tA.textContent = S.mode === "side" ? "A · " + imgTitle(S.a)
    : S.mode === "flip" ? (S.flipShowB ? "B · " + imgTitle(S.b) : "A · " + imgTitle(S.a)) + "  (F to flip)"
      : S.mode === "wipe" ? `A · ${S.a.label}  |  B · ${S.b.label}` : `A − B · ${S.kind}`;
  $("#zoom-out").textContent = `${S.scale.toFixed(S.scale < 1 ? 2 : 1)} screen px per pixel` +
    (S.bin > 1 ? ` · means over ${S.bin}×${S.bin} pixels` : "");
  const zs = $("#zoom"), preset = [1, 2, 4, 8, 16].find((z) => Math.abs(z - S.scale) < 1e-9);
  if (S.fit) zs.value = "fit";
  else if (preset) zs.value = String(preset);
  else { $("#zoom-custom").textContent = S.scale.toFixed(2) + "×"; zs.value = "custom"; }
}
function zoomTo(z, cx, cy) {   // z screen px per common-grid pixel, about canvas point (cx, cy)
  const r = cvA.getBoundingClientRect();
  const fit = Math.min(r.width / S.W, r.height / S.H);
  if (z <= fit) { fitView(); return draw(); }
  z = Math.min(16, z);
  if (cx === undefined) { cx = r.width / 2; cy = r.height / 2; }
  const px = S.ox + cx / S.scale, py = S.oy + cy / S.scale;
  S.scale = z; S.ox = px - cx / z; S.oy = py - cy / z; S.fit = false;
  draw();
}
function pixelAt(cv, ev) {
  const r = cv.getBoundingClientRect();
  return { cx: ev.clientX - r.left, cy: ev.clientY - r.top,
    x: Math.floor(S.ox + (ev.clientX - r.left) / S.scale), y: Math.floor(S.oy + (ev.clientY - r.top) / S.scale) };
}
function rgbAt(img, x, y) {
  const i = sample(img, x, y, S.W, S.H), n = img.w * img.h;
  return [img.px[i], img.px[n + i], img.px[2 * n + i]];
}
function setRow(id, v) {
  const tr = $(id), tds = tr.querySelectorAll("td");
  tr.dataset.rgb = v ? JSON.stringify(v) : "";
  tds.forEach((td, k) => { td.textContent = v ? fmtV(v[k]) : ""; });
}
function readout(x, y) {
  const inside = S.linA && x >= 0 && y >= 0 && x < S.W && y < S.H;
  S.last = { x, y };
  S.hover = inside ? { x, y } : null;
  $("#ro-xy").textContent = inside ? `x ${x}, y ${y}` : "—";
  $("#ro-note").textContent = inside && S.bin > 1 ? `block means over ${S.bin}×${S.bin} pixels (at the silhouette including background)` : "";
  const a = inside ? rgbAt(S.linA, x, y) : null, b = inside ? rgbAt(S.linB, x, y) : null;
  setRow("#ro-a", a); setRow("#ro-b", b); setRow("#ro-d", a && b ? a.map((v, k) => v - b[k]) : null);
  let region = 0;
  if (inside && S.labels && S.labels.px) region = S.labels.px[sample(S.labels, x, y, S.W, S.H)];
  const name = region > 0 && region <= M.regions.names.length ? M.regions.names[region - 1] : null;
  const ro = $("#ro-region");
  ro.textContent = !inside ? "—" : !S.labels ? "not computed (no reference)" : name || "none";
  ro.dataset.region = name || "";
  if (region !== S.region) { S.region = region; regionTable(); }
  draw();
}
function numbers() {
  const box = $("#numbers");
  box.textContent = "";
  for (const [tag, e] of [["A", S.a], ["B", S.b]]) {
    const rows = [["time", e.seconds == null ? "–" : fmtS(e.seconds) + (e.irradiance_seconds != null ? " + " + fmtS(e.irradiance_seconds) + " irradiance" : "")]];
    if (e.kind === "reference") {
      if (e.spp) rows.push(["samples", Math.round(e.spp) + " spp per pixel"]);
      rows.push(["pixels", `${e.width} × ${e.height} (box-filtered camera blocks)`]);
    } else {
      const t = e.truth;
      rows.push(["to the truth", t ? `${pm(t.distance, t.stderr)}${t.resolved ? "" : " (not resolved)"}` : "– (" + (e.geometry !== "high" ? "reference is of the high mesh" : "no reference") + ")"]);
      if (t && t.rank) rows.push(["rank", `${t.rank}${t.rank_range && t.rank_range[0] !== t.rank_range[1] ? ` (${t.rank_range[0]}–${t.rank_range[1]})` : ""} on ${t.scale}×${t.scale} blocks`]);
      if (e.flip) rows.push(["FLIP vs truth", e.flip.mean.toFixed(3)]);
      if (e.baseline) rows.push([`to ${e.baseline.label}`, `${pm(e.baseline.rel_rmse, e.baseline.noise)} · SSIM ${e.baseline.ssim.toFixed(3)}`]);
    }
    box.append(el("h3", {}, `${tag} · ${e.label}`, el("span", { class: "muted small", text: `${e.light}${e.kind === "model" ? " · " + e.geometry : ""}` })),
      el("table", { class: "facts-table num" }, rows.map(([k, v]) => el("tr", {}, el("th", { text: k }), el("td", { text: v })))));
  }
  box.append(el("div", { class: "muted small", text: "relative RMSE ± what the images' own noise alone gives (1 s.e. for the truth, on the reference's pixels)" }));
}
function regionTable() {
  const tb = $("#region-table");
  tb.textContent = "";
  const ref = IMAGES.find((e) => e.kind === "reference" && e.light === S.a.light);
  const names = M.regions.names;
  const head = el("tr", {}, el("th", { text: "region" }), el("th", { text: "ref. lum." }), el("th", { text: "A" }), el("th", { text: "B" }));
  tb.append(el("thead", {}, head));
  const body = el("tbody");
  names.forEach((name, k) => {
    const col = M.regions.colours[k + 1];
    const cell = (e) => {
      const g = e && e.truth && e.truth.regions[name];
      if (!g) return el("td", { class: "unres-num", text: e && e.kind === "reference" ? "ref." : "–" });
      return el("td", { class: g.resolved ? "" : "unres-num", text: pm(g.rel_diff, g.stderr, 0) });
    };
    const rr = ref && ref.regions[name];
    const lum = rr ? rr.ref_mean_rgb.reduce((s, v, c) => s + LUM[c] * v, 0) : null;
    body.append(el("tr", { class: S.region === k + 1 ? "hl" : "", "data-region": name },
      el("td", {}, el("span", { class: "swatch", style: `background: rgb(${col})` }), name.replace("_", " ")),
      el("td", { text: lum == null ? "–" : lum.toPrecision(3) + (rr.ref_rel_se != null ? ` ± ${(100 * rr.ref_rel_se).toFixed(0)} %` : "") }),
      cell(S.a), cell(S.b)));
  });
  tb.append(body);
  $("#regions-box").hidden = !ref;
}
function relayout(change) {   // a panel changes size: keep the image point at its centre
  const r = cvA.getBoundingClientRect();
  const c = { x: S.ox + r.width / 2 / S.scale, y: S.oy + r.height / 2 / S.scale };
  change();
  if (!S.linA) return draw();
  if (S.fit) fitView();
  else { const q = cvA.getBoundingClientRect(); S.ox = c.x - q.width / 2 / S.scale; S.oy = c.y - q.height / 2 / S.scale; }
  draw();
}
function setMode(m) {
  document.querySelectorAll("#mode button").forEach((b) => b.classList.toggle("on", b.dataset.mode === m));
  relayout(() => { S.mode = m; $("#stage").className = "stage " + (m === "side" ? "side" : "single"); });
}
function setKind(k) {
  S.kind = k; S.diffSrc = null;
  document.querySelectorAll("#diffkind button").forEach((b) => b.classList.toggle("on", b.dataset.kind === k));
  draw();
}

// ------------------------------------------------------------------ timings and conclusions
function buildTimings() {
  const sec = $("#timings");
  const models = uniq(IMAGES.filter((e) => e.kind === "model").map((e) => e.model));
  const geoms = uniq(IMAGES.filter((e) => e.kind === "model").map((e) => e.geometry));
  const lights = uniq(IMAGES.filter((e) => e.kind === "model").map((e) => e.light));
  const t = el("table", { class: "big" });
  t.append(el("thead", {}, el("tr", {}, el("th", { text: "model / geometry" }), lights.map((l) => el("th", { text: l })))));
  const body = el("tbody");
  for (const m of models) for (const g of geoms) {
    const cells = lights.map((l) => IMAGES.find((e) => e.kind === "model" && e.model === m && e.geometry === g && e.light === l));
    if (!cells.some(Boolean)) continue;
    body.append(el("tr", {}, el("td", { text: `${cells.find(Boolean).label} / ${g}` }),
      cells.map((e) => el("td", { text: !e || e.seconds == null ? "–" : fmtS(e.seconds) + (e.irradiance_seconds != null ? " + " + fmtS(e.irradiance_seconds) : "") }))));
  }
  const refs = IMAGES.filter((e) => e.kind === "reference");
  if (refs.length) body.append(el("tr", {}, el("td", { text: "reference (path traced)" }),
    lights.map((l) => { const r = refs.find((e) => e.light === l); return el("td", { text: r ? fmtS(r.seconds) : "–" }); })));
  t.append(body);
  const T = M.thesis_times, tt = el("table", { class: "big" });
  tt.append(el("thead", {}, el("tr", {}, el("th", { text: "model / triangles" }), T.lights.map((l) => el("th", { text: l })))));
  const tb = el("tbody");
  for (const [mesh, byLight] of Object.entries(T.times))
    T.models.forEach((m, k) => tb.append(el("tr", {}, el("td", { text: `${T.labels[k]} / ${mesh}` }), T.lights.map((l) => el("td", { text: byLight[l][k] })))));
  tt.append(tb);
  sec.append(el("h2", { class: "section", text: "Seconds per image" }),
    el("div", { class: "tables" },
      el("div", {}, el("h3", { text: "this run" + (M.device ? " · " + M.device : "") }), t),
      el("div", {}, el("h3", { text: "the thesis (Arizpe 2006), m:ss, pbrt on a dual-core Xeon 2.4 GHz" }), tt)),
    el("p", { class: "note", text: "Each image's own work (shading; for a BSSRDF the gather, the exit and the surface term); " +
      "'+ x' is the BSSRDF's irradiance pass for that light and mesh, shared by every image on that mesh. " +
      "The camera and shadow rays every model of a mesh and light shares are cast once and not counted. " +
      "Hardware differs from the thesis's: compare ratios between models under one light, not absolute times." }));
}
function verdictPill(v) {
  const cls = v === M.verdicts.holds ? "holds" : v === M.verdicts.fails ? "fails" : "unres";
  return el("span", { class: "pill " + cls, text: v });
}
function buildConclusions() {
  const sec = $("#conclusions");
  sec.append(el("h2", { class: "section", text: "The thesis's conclusions against the path-traced reference" }));
  if (!M.thesis.length) {
    sec.append(el("p", { class: "note", text: M.truth_skipped || "No reference in this run: the conclusions are not tested." }));
  } else {
    sec.append(el("div", { class: "claims" }, M.thesis.map((c) => el("div", { class: "claim" },
      el("div", { class: "head" }, verdictPill(c.verdict), el("span", { text: `${labelOf(c.model)}: ${c.claim}` })),
      el("div", { class: "per" }, Object.entries(c.per_light || {}).map(([l, v]) => el("span", {}, `${l}: `, verdictPill(v))))))));
  }
  const refs = IMAGES.filter((e) => e.kind === "reference" && e.ranking && e.ranking.length);
  if (refs.length) {
    sec.append(el("h2", { class: "section", text: "Ranking by distance to the reference" }));
    const t = el("table", { class: "big" });
    t.append(el("thead", {}, el("tr", {}, el("th", { text: "lighting" }), el("th", { text: "closest first" }))));
    t.append(el("tbody", {}, refs.map((r) => el("tr", {}, el("td", { text: r.light }), el("td", { text: r.ranking.map(labelOf).join("  ›  ") })))));
    sec.append(el("div", { class: "tables" }, t));
  }
}
function labelOf(model) { const e = IMAGES.find((x) => x.model === model); return e ? e.label : model; }

// ------------------------------------------------------------------ wiring
function showTab(name) {
  document.querySelectorAll("section.tab").forEach((s) => { s.hidden = s.id !== name; });
  document.querySelectorAll("#tabs button").forEach((b) => b.classList.toggle("on", b.dataset.tab === name));
  if (name === "compare" && !S.a && IMAGES.length) { const e = IMAGES[0]; openCompare(e.id, defaultPartner(e).id); }
  else if (name === "compare") requestAnimationFrame(() => { if (S.fit && S.linA) fitView(); draw(); });
}
function init() {
  $("#scene-name").textContent = `${M.scene} · ${IMAGES.length} images · interactive comparison`;
  document.querySelectorAll("#tabs button").forEach((b) => b.addEventListener("click", () => showTab(b.dataset.tab)));
  const base = IMAGES.find((e) => e.model === M.baseline);
  $("#grid-note").textContent = "Under each image: its seconds; its distance to the path-traced reference " +
    "(relative RMSE on 4×4 blocks of reference pixels ± 1 standard error of both images' noise; n.r.: not resolved)" +
    (base ? `; its distance to ${base.label} (relative RMSE ± what the two images' noise alone gives)` : "") +
    ". Click an image to compare it with the reference pixel by pixel.";
  if (M.truth_skipped) $("#grid-note").textContent += " " + M.truth_skipped;
  buildFilters(); buildGrid(); buildTimings(); buildConclusions();
  fillSelect($("#sel-a")); fillSelect($("#sel-b"));
  $("#sel-a").addEventListener("change", (ev) => openCompare(ev.target.value, S.b.id));
  $("#sel-b").addEventListener("change", (ev) => openCompare(S.a.id, ev.target.value));
  $("#swap").addEventListener("click", () => openCompare(S.b.id, S.a.id));
  document.querySelectorAll("#mode button").forEach((b) => b.addEventListener("click", () => setMode(b.dataset.mode)));
  document.querySelectorAll("#diffkind button").forEach((b) => b.addEventListener("click", () => setKind(b.dataset.kind)));
  $("#exposure").addEventListener("input", (ev) => { S.stops = +ev.target.value; $("#exposure-out").textContent = S.stops.toFixed(1); retone(); draw(); });
  $("#bin").addEventListener("change", (ev) => setBin(+ev.target.value));
  $("#regions-on").addEventListener("change", (ev) => { S.showRegions = ev.target.checked; draw(); });
  $("#tonemap").addEventListener("change", (ev) => { S.tone = ev.target.value; retone(); draw(); });
  $("#zoom").addEventListener("change", (ev) => { if (ev.target.value === "fit") { fitView(); draw(); } else zoomTo(+ev.target.value); });
  $("#diffscale").addEventListener("change", (ev) => { const v = +ev.target.value; if (v > 0) { S.diffScale[S.a.id + "|" + S.b.id + "|" + S.kind] = v; S.diffSrc = null; draw(); } });
  for (const cv of [cvA, cvB]) {
    let drag = null;
    cv.addEventListener("wheel", (ev) => { ev.preventDefault(); const p = pixelAt(cv, ev); zoomTo(S.scale * (ev.deltaY < 0 ? 1.25 : 0.8), p.cx, p.cy); }, { passive: false });
    cv.addEventListener("mousedown", (ev) => {
      const p = pixelAt(cv, ev), w = cv.getBoundingClientRect().width;
      drag = S.mode === "wipe" && Math.abs(p.cx - S.wipe * w) < 12 ? { wipe: true } : { x: ev.clientX, y: ev.clientY, ox: S.ox, oy: S.oy };
    });
    window.addEventListener("mouseup", () => { drag = null; });
    cv.addEventListener("mousemove", (ev) => {
      if (drag && drag.wipe) { const r = cv.getBoundingClientRect(); S.wipe = Math.max(0, Math.min(1, (ev.clientX - r.left) / r.width)); }
      else if (drag) { S.ox = drag.ox - (ev.clientX - drag.x) / S.scale; S.oy = drag.oy - (ev.clientY - drag.y) / S.scale; S.fit = false; }
      const p = pixelAt(cv, ev);
      readout(p.x, p.y);
    });
    cv.addEventListener("mouseleave", () => { S.hover = null; draw(); });
  }
  window.addEventListener("keydown", (ev) => {
    if ($("#compare").hidden || ev.target.tagName === "INPUT" || ev.target.tagName === "SELECT") return;
    if (ev.key === "f" || ev.key === "F" || ev.key === " ") { ev.preventDefault(); if (S.mode !== "flip") setMode("flip"); else { S.flipShowB = !S.flipShowB; draw(); } }
    else if (ev.key === "s" || ev.key === "S") openCompare(S.b.id, S.a.id);
    else if (ev.key === "0") { fitView(); draw(); }
    else if ("12345".includes(ev.key)) zoomTo(2 ** (+ev.key - 1));
    else if (ev.key.startsWith("Arrow") && S.last) {   // the read-out one pixel further
      ev.preventDefault();
      const d = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] }[ev.key];
      readout(Math.max(0, Math.min(S.W - 1, S.last.x + d[0])), Math.max(0, Math.min(S.H - 1, S.last.y + d[1])));
    }
  });
  window.addEventListener("resize", () => { if (S.fit && S.linA) fitView(); draw(); });
}
window.dermis = {
  manifest: M, ready: false, state: S, open: openCompare, setMode, setKind, zoomTo,
  // client coordinates of the centre of common-grid pixel (x, y) in panel A
  centre(x, y) { const r = cvA.getBoundingClientRect(); S.ox = x + 0.5 - r.width / 2 / S.scale; S.oy = y + 0.5 - r.height / 2 / S.scale; S.fit = false; draw(); },
  clientOf(x, y) { const r = cvA.getBoundingClientRect(); return { x: r.left + (x + 0.5 - S.ox) * S.scale, y: r.top + (y + 0.5 - S.oy) * S.scale }; },
};
init();
})();
