// The web page's behaviour: plain JavaScript, no libraries, talks only to
// this service (same origin). One file: /v1/analyze (estimate, spectrum,
// diagnostics), /v1/preview (original with the camera's white balance, and
// the corrected image, downsized), /v1/white-balance (downloads). Batch:
// /v1/batches, polled.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";  // the SVG namespace name, not a fetched URL

// What the page says of each method ("The light was estimated by ..."): the estimator
// registry's own words (recovery/methods.py), from GET /v1/models when the page loads.
let METHOD_WORDS = {};

const SOURCE_WORDS = {
  "measured": "measured spectral sensitivities",
  "matrix-derived": "sensitivities derived from the file's colour matrix (approximate)",
  "uploaded": "the sensitivities you uploaded",
  "generic": "a generic camera, because this one is not known (approximate)",
};

const ERROR_WORDS = {
  "unsupported_format": "This is not a file the service can read",
  "not_linear": "This image is not linear data",
  "corrupt_file": "The file is damaged or truncated",
  "empty_file": "The file is empty",
  "file_too_large": "The file is too large",
  "too_large": "The request is too large",
  "too_many_pixels": "The image has too many pixels",
  "non_finite": "The image contains invalid numbers",
  "invalid_parameter": "An option is not valid",
  "missing_file": "No file was sent",
  "unknown_camera": "The camera is not known",
  "no_color_matrix": "The file has no colour matrix",
  "not_found": "Not found",
  "internal_error": "The service failed (please report this)",
  "not_camera_raw": "No camera sensor data to analyse",
  "unusable_neutral": "That spot cannot be used as white",
  "no_temperature": "The light has no colour temperature",
  "no_as_shot_white": "The file has no as-shot white balance",
  "too_many_items": "Too many files",
  "name_too_long": "A file name is too long",
  "insufficient_storage": "The server's disk is full",
  "camera_mismatch": "The files come from different cameras",
};

// ---------------------------------------------------------------- helpers

function fmt(x, digits) {
  return (typeof x === "number" && isFinite(x)) ? x.toFixed(digits) : "–";
}

function percent(x) {
  return fmt(100 * x, x < 0.01 ? 2 : 1) + " %";
}

// An Error whose message is the API's {"error","detail"} in words.
class ApiError extends Error {
  constructor(status, code, detail) {
    // the server's detail always shows; a code without words of its own shows the detail alone
    const words = ERROR_WORDS[code];
    super(`${words ? words + ": " : ""}${detail} (HTTP ${status}, ${code})`);
    this.status = status;
    this.code = code;
  }
}

async function failure(resp) {
  let body = null;
  try { body = await resp.json(); } catch (e) { /* not JSON */ }
  if (body && typeof body.error === "string") {
    return new ApiError(resp.status, body.error, typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail));
  }
  return new ApiError(resp.status, "http_error", resp.statusText || "no explanation given");
}

async function post(url, form) {
  let resp;
  try {
    resp = await fetch(url, {method: "POST", body: form});
  } catch (e) {
    throw new Error(`Could not reach the service (${e.message}).`);
  }
  if (!resp.ok) throw await failure(resp);
  return resp;
}

function showError(el, err) {
  el.textContent = err.message;
  el.hidden = false;
}

function options() {
  const o = {};
  for (const el of $("options").elements) {
    if (el.name && el.value !== "") o[el.name] = el.value;
  }
  return o;
}

function formFor(file, extra) {
  const fd = new FormData();
  fd.append("file", file, file.name);
  for (const [k, v] of Object.entries(extra)) fd.append(k, v);
  return fd;
}

function saveBlob(blob, name) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = name;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(a.href), 60000);
}

function stem(name) {
  return name.replace(/\.[^.]*$/, "") || "image";
}

function setImage(img, blob) {
  return new Promise((resolve, reject) => {
    if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
    img.onload = () => resolve();
    img.onerror = () => reject(new Error("the browser could not display the preview image"));
    img.src = URL.createObjectURL(blob);
  });
}

// ---------------------------------------------------------------- options

async function loadOptions() {
  try {
    const [models, cameras] = await Promise.all([
      fetch("/v1/models").then((r) => r.json()), fetch("/v1/cameras").then((r) => r.json())]);
    METHOD_WORDS = models.method_words || {};
    const method = $("opt-method");
    for (const m of models.methods || []) {
      if (m !== "auto") method.add(new Option(m, m));
    }
    const target = $("opt-target");
    for (const name of models.illuminants || []) {
      if (name !== "D65") target.add(new Option(name, name));
    }
    const camera = $("opt-camera");
    for (const c of cameras.cameras || []) camera.add(new Option(`${c.name} (measured)`, c.name));
  } catch (e) {
    // the defaults in the HTML still work
  }
}

// ---------------------------------------------------------------- words

function diagnosticsInWords(j) {
  const d = j.diagnostics || {};
  const method = j.method || d.method || "unknown";
  let summary = method === "neutral-surface"
    ? "The white was taken from the surface you clicked (its mean colour is used as the light)."
    : `The light was estimated by ${METHOD_WORDS[method] || method}.`;
  const why = d.decided_by || (typeof d.decision === "string" ? d.decision.replace(/^[\w-]+: /, "") : "");
  if (why) summary += ` It was decided by ${why}.`;
  if (typeof d.confidence === "number") {
    const low = d.low_confidence === undefined ? d.confidence < 0.4 : d.low_confidence;
    const level = low ? "low" : d.confidence >= 0.75 ? "high" : "moderate";
    summary += ` Confidence is ${level} (${fmt(100 * d.confidence, 0)} %).`;
  }

  const details = [];
  const cam = j.camera || {};
  if (cam.name) details.push(`Camera: ${cam.name}, with ${SOURCE_WORDS[cam.source] || cam.source}.`);
  if (typeof d.pixels_used === "number" && typeof d.pixels_total === "number") {
    let s = `It used ${d.pixels_used.toLocaleString("en")} of ${d.pixels_total.toLocaleString("en")} analysis pixels`;
    const excluded = d.pixels_dark_or_saturated ?? ((d.pixels_dark || 0) + (d.pixels_saturated || 0));
    if (excluded) s += ` (${excluded.toLocaleString("en")} dark or saturated left out)`;
    details.push(s + ".");
  }
  if (typeof d.posterior_spread_deg === "number") {
    details.push(`The probable lights lie within about ${fmt(d.posterior_spread_deg, 1)}° of each other ` +
      "(angle between camera responses).");
  }
  if (typeof d.generic_vs_matrix_deg === "number") {
    details.push(`With the generic camera, the estimate is ${fmt(d.generic_vs_matrix_deg, 1)}° from the one made ` +
      `with the file's colour matrix; the confidence was multiplied by ${fmt(d.confidence_factor_generic, 2)}.`);
  }
  if (d.top_candidates) details.push(`Most probable lights of the candidate set: ${d.top_candidates}.`);
  if (typeof d.subspace_fit_ratio === "number") {
    const good = d.subspace_fit_ratio <= 0.1;
    details.push(`The surfaces' camera responses ${good ? "fit" : "do not fit"} a ${d["D(S)"] ?? "low"}-dimensional ` +
      `subspace: smallest to next singular value ${fmt(d.subspace_fit_ratio, 3)} (a good fit is at most 0.1).`);
  }
  if (d["D(S)"] !== undefined && d["D(E)"] !== undefined) {
    details.push(`Linear models: ${d["D(S)"]} surface terms (${d.surface_model || "default"}), ` +
      `${d["D(E)"]} light terms (${d.light_model || "default"}).`);
  } else if (d.light_model) {
    details.push(`Light spectrum: ${d.light_model}.`);
  }
  if (typeof d.lighting_condition === "number") {
    const ill = d.lighting_condition > 100;
    details.push(`The lighting matrix has condition number ${fmt(d.lighting_condition, 1)}` +
      (ill ? ": ill conditioned, so the surface estimates are unreliable." : "."));
  }
  const nonphys = d.nonphysical_reflectance_fraction ?? d.negative_reflectance_fraction;
  if (typeof nonphys === "number" && nonphys > 0) {
    details.push(`${percent(nonphys)} of the recovered reflectances are non-physical (outside 0 to 1).`);
  }
  if (typeof d.nonphysical_light_fraction === "number" && d.nonphysical_light_fraction > 0) {
    details.push(`The estimated spectrum is negative at ${percent(d.nonphysical_light_fraction)} of wavelengths.`);
  }
  if (j.as_shot && typeof j.as_shot.angle_to_estimate_deg === "number") {
    details.push(`The camera's own as-shot white balance is ${fmt(j.as_shot.angle_to_estimate_deg, 1)}° ` +
      "from this estimate.");
  }
  return {summary, details, warnings: (j.warnings || []).map((w) => pageWords(String(w)))};
}

// The server's warnings name API parameters; on the page they are clicks and buttons.
function pageWords(w) {
  return w.replace("use a white surface ('neutral') or white=as-shot",
    "click a white or grey surface in either image, or use the camera's own white (Download as-shot PNG)");
}

function lightFacts(il) {
  if (typeof il.cct === "number" && isFinite(il.cct)) {
    $("cct").textContent = `${Math.round(il.cct)} K`;
  } else {
    $("cct").textContent = "undefined (the light is too far from the Planckian locus)";
  }
  $("duv").textContent = (typeof il.duv === "number") ? (il.duv >= 0 ? "+" : "") + il.duv.toFixed(4) : "–";
  // the same chromaticity on Adobe's scale: Temperature within a few kelvin of the CCT, Tint about 3000 x Duv
  $("temp-tint").textContent = (typeof il.temperature === "number" && typeof il.tint === "number")
    ? `${Math.round(il.temperature)} K / ${il.tint >= 0 ? "+" : ""}${Math.round(il.tint)}` : "–";
  const rgb = il.camera_rgb || [];
  const g = rgb[1] || 1;
  $("camera-rgb").textContent = rgb.map((v) => fmt(v / g, 3)).join(" : ");
  $("wb-mult").textContent = (il.wb_multipliers || []).map((v) => fmt(v, 3)).join(", ");
}

// ---------------------------------------------------------------- spectrum plot

// Approximate display colour of a wavelength (for the fill under the curve only).
function wavelengthColour(nm) {
  let r = 0, g = 0, b = 0;
  if (nm < 440) { r = (440 - nm) / 60; b = 1; } else if (nm < 490) { g = (nm - 440) / 50; b = 1; }
  else if (nm < 510) { g = 1; b = (510 - nm) / 20; } else if (nm < 580) { r = (nm - 510) / 70; g = 1; }
  else if (nm < 645) { r = 1; g = (645 - nm) / 65; } else { r = 1; }
  const c = (v) => Math.round(255 * Math.max(0, Math.min(1, v)) ** 0.8);
  return `rgb(${c(r)},${c(g)},${c(b)})`;
}

function el(name, attrs, text) {
  const e = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

function plotSpectrum(container, wl, spd) {
  container.textContent = "";
  const W = 480, H = 260, L = 52, R = 12, T = 12, B = 40;
  const svg = el("svg", {viewBox: `0 0 ${W} ${H}`, width: W, height: H, role: "img", id: "spectrum-svg",
    "aria-label": "relative spectral power of the estimated light"});
  const pts = wl.map((x, i) => [x, spd[i]]).filter(([x, y]) => isFinite(x) && isFinite(y));
  if (pts.length < 2) {
    svg.appendChild(el("text", {x: W / 2, y: H / 2, "text-anchor": "middle"}, "no spectrum"));
    container.appendChild(svg);
    return;
  }
  const x0 = Math.min(...pts.map((p) => p[0])), x1 = Math.max(...pts.map((p) => p[0]));
  const ymax = Math.max(...pts.map((p) => p[1])) || 1;
  const ymin = Math.min(0, ...pts.map((p) => p[1] / ymax));
  const sx = (x) => L + (x - x0) / (x1 - x0) * (W - L - R);
  const sy = (y) => T + (1 - (y - ymin) / (1 - ymin)) * (H - T - B);

  const grad = el("linearGradient", {id: "spectrum-gradient", x1: "0", x2: "1", y1: "0", y2: "0"});
  for (let k = 0; k <= 10; k++) {
    const nm = x0 + k / 10 * (x1 - x0);
    grad.appendChild(el("stop", {offset: `${k * 10}%`, "stop-color": wavelengthColour(nm)}));
  }
  const defs = el("defs");
  defs.appendChild(grad);
  svg.appendChild(defs);

  // axes and ticks
  svg.appendChild(el("line", {x1: L, y1: sy(ymin), x2: L, y2: T, class: "axis"}));
  svg.appendChild(el("line", {x1: L, y1: sy(0), x2: W - R, y2: sy(0), class: "axis"}));
  for (let x = Math.ceil(x0 / 50) * 50; x <= x1; x += 50) {
    svg.appendChild(el("line", {x1: sx(x), y1: sy(ymin), x2: sx(x), y2: sy(ymin) + 4, class: "axis"}));
    svg.appendChild(el("text", {x: sx(x), y: sy(ymin) + 16, "text-anchor": "middle", class: "tick"}, `${x}`));
  }
  for (const y of [0, 0.5, 1]) {
    svg.appendChild(el("line", {x1: L - 4, y1: sy(y), x2: L, y2: sy(y), class: "axis"}));
    svg.appendChild(el("text", {x: L - 7, y: sy(y) + 4, "text-anchor": "end", class: "tick"}, y.toFixed(1)));
  }
  svg.appendChild(el("text", {x: (L + W - R) / 2, y: H - 6, "text-anchor": "middle", class: "label"},
    "wavelength (nm)"));
  svg.appendChild(el("text", {x: 14, y: (T + H - B) / 2, "text-anchor": "middle", class: "label",
    transform: `rotate(-90 14 ${(T + H - B) / 2})`}, "relative power"));

  const line = pts.map(([x, y], i) => `${i ? "L" : "M"}${sx(x).toFixed(1)},${sy(y / ymax).toFixed(1)}`).join(" ");
  svg.appendChild(el("path", {d: `${line} L${sx(x1).toFixed(1)},${sy(0).toFixed(1)} L${sx(x0).toFixed(1)},` +
    `${sy(0).toFixed(1)} Z`, fill: "url(#spectrum-gradient)", "fill-opacity": "0.35", stroke: "none"}));
  svg.appendChild(el("path", {d: line, id: "spectrum-path", class: "curve"}));
  container.appendChild(svg);
}

// ---------------------------------------------------------------- one file

let current = null;   // {file, options, estimate}

function chooseFile(file) {
  current = file ? {file} : null;
  $("file-name").textContent = file ? `${file.name} (${(file.size / 1e6).toFixed(2)} MB)` : "no file chosen";
  $("run").disabled = !file;
  if (file) run();
}

async function run() {
  if (!current) return;
  const file = current.file;
  const opts = options();
  current.options = opts;
  $("error").hidden = true;
  $("result").hidden = true;
  $("run").disabled = true;
  $("status").textContent = `Analysing ${file.name}…`;
  const t0 = performance.now();
  const analyzeOpts = {};
  for (const k of ["camera", "method", "quality"]) if (opts[k]) analyzeOpts[k] = opts[k];
  if (current.neutral) analyzeOpts.neutral = JSON.stringify(current.neutral);
  const previewOpts = Object.assign({}, analyzeOpts, {target: opts.target || "D65", format: "jpeg", max_side: "1024"});
  try {
    const [analysis, original, corrected] = await Promise.all([
      post("/v1/analyze", formFor(file, analyzeOpts)).then((r) => r.json()),
      post("/v1/preview", formFor(file, {wb: "camera", format: "jpeg", max_side: "1024"})),
      post("/v1/preview", formFor(file, Object.assign({wb: "corrected"}, previewOpts))),
    ]);
    if (current === null || current.file !== file) return;   // another file was chosen meanwhile
    current.estimate = analysis;
    const noteOf = (resp) => {
      try { return JSON.parse(resp.headers.get("X-Preview") || "{}"); } catch (e) { return {}; }
    };
    const on = noteOf(original), cn = noteOf(corrected);
    await Promise.all([setImage($("img-original"), await original.blob()),
      setImage($("img-corrected"), await corrected.blob())]);
    $("original-note").textContent = (on.warnings || []).join("; ");
    $("corrected-target").textContent = opts.target === "estimate" ? "the estimated light (as seen)" : (opts.target || "D65");
    // the previews show what the downloads hold (the DNG DefaultCrop): caption
    // that size; clicks map through the crop to the decoded image's pixels
    const outW = cn.output_width || cn.full_width, outH = cn.output_height || cn.full_height;
    $("corrected-note").textContent = outW ? `(preview ${cn.width}×${cn.height}; the downloads are ${outW}×${outH})` : "";
    current.full = cn.full_width ? {w: cn.full_width, h: cn.full_height,
      crop: cn.crop || [0, 0, cn.full_height, cn.full_width]} : null;
    showNeutral(analysis);
    const failed = analysis.method_failed;
    $("corrected-flag").hidden = !failed;
    $("corrected-flag").textContent = failed ? "Not trustworthy: the literal Maloney–Wandell method failed on this " +
      `image by its own tests: ${failed.reasons.join("; ")}.` : "";

    const il = analysis.illuminant || {};
    lightFacts(il);
    plotSpectrum($("spectrum"), il.wavelengths || [], il.spectrum || []);
    const words = diagnosticsInWords(analysis);
    $("diag-summary").textContent = words.summary;
    const fill = (ul, items, prefix) => {
      ul.textContent = "";
      for (const s of items) { const li = document.createElement("li"); li.textContent = prefix + s; ul.appendChild(li); }
    };
    fill($("diag-details"), words.details, "");
    fill($("diag-warnings"), words.warnings, "Warning: ");
    $("result").hidden = false;
    $("status").textContent = `Done in ${((performance.now() - t0) / 1000).toFixed(1)} s.`;
  } catch (err) {
    $("status").textContent = "";
    showError($("error"), err);
  } finally {
    $("run").disabled = !current;
  }
}

async function downloadCorrected(format, ext, white = "estimate") {
  if (!current || !current.options) return;
  const o = current.options;
  const fields = {format, white};
  for (const k of ["camera", "method", "quality", "target"]) if (o[k]) fields[k] = o[k];
  if (current.neutral && white === "estimate") fields.neutral = JSON.stringify(current.neutral);
  $("dl-status").textContent = `Rendering the full-resolution ${format.toUpperCase()}…`;
  $("error").hidden = true;
  try {
    const resp = await post("/v1/white-balance", formFor(current.file, fields));
    const name = format === "xmp" ? `${stem(current.file.name)}.xmp`
      : `${stem(current.file.name)}-${white === "as-shot" ? "as-shot" : "corrected"}.${ext}`;
    saveBlob(await resp.blob(), name);
    $("dl-status").textContent = "";
  } catch (err) {
    $("dl-status").textContent = "";
    showError($("error"), err);
  }
}

// "Use this as white": a click on either image fixes the light from a small
// square around that point (about 1 % of the long side), in full-resolution
// pixels (the previews' X-Preview header gives the full size).
function neutralFromClick(img, ev) {
  if (!current || !current.full) return;
  const box = img.getBoundingClientRect();
  if (!box.width || !box.height) return;
  const {w: W, h: H, crop: [top, left, ch, cw]} = current.full;
  const fx = Math.min(Math.max((ev.clientX - box.left) / box.width, 0), 1);
  const fy = Math.min(Math.max((ev.clientY - box.top) / box.height, 0), 1);
  const r = Math.min(H - 1, top + Math.floor(fy * ch)), c = Math.min(W - 1, left + Math.floor(fx * cw));
  const half = Math.max(2, Math.round(0.005 * Math.max(W, H)));
  current.neutral = [Math.max(0, r - half), Math.max(0, c - half), Math.min(H, r + half + 1), Math.min(W, c + half + 1)];
  run();
}

function showNeutral(analysis) {
  const n = analysis && analysis.neutral;
  $("neutral-clear").hidden = !current.neutral;
  if (n) {
    const ang = typeof n.angle_to_estimate_deg === "number" ? `, ${fmt(n.angle_to_estimate_deg, 1)}° from the estimate` : "";
    $("neutral-note").textContent = `White fixed from the surface at rows ${n.where[0]}–${n.where[2]}, ` +
      `columns ${n.where[1]}–${n.where[3]} (${n.cells_used} cells${ang}). Click elsewhere to change it.`;
  } else {
    $("neutral-note").textContent = "Click a white or grey surface in either image to use it as white.";
  }
}

function downloadEstimate() {
  if (!current || !current.estimate) return;
  const blob = new Blob([JSON.stringify(current.estimate, null, 2)], {type: "application/json"});
  saveBlob(blob, `${stem(current.file.name)}-estimate.json`);
}

// ---------------------------------------------------------------- batch

let batchFiles = [];
let batch = null;   // {id, timer}

function chooseBatch(files) {
  batchFiles = Array.from(files || []);
  $("batch-names").textContent = batchFiles.length
    ? `${batchFiles.length} file${batchFiles.length > 1 ? "s" : ""}: ${batchFiles.map((f) => f.name).join(", ")}`
    : "no files chosen";
  $("batch-run").disabled = batchFiles.length === 0;
}

function itemLink(id, item, index) {
  // by index, never by name: a file named "0" must not take item 0's link
  const href = item.url ||
    `/v1/batches/${encodeURIComponent(id)}/items/by-index/${encodeURIComponent(item.index ?? index)}`;
  const a = document.createElement("a");
  a.href = href;
  a.textContent = "download";
  a.setAttribute("download", "");
  return a;
}

// Over and every count final: the API's "settled" (a cancelled batch's items
// that were running keep answering for a moment: done, kept, or cancelled).
function batchSettled(j) {
  const c = j.counts || {};
  const over = ["done", "cancelled", "failed"].includes(j.status);
  if (typeof j.settled === "boolean") return j.settled;
  return over && !(c.pending || 0) && !(c.running || 0);
}

function renderBatch(j) {
  const c = j.counts || {};
  const done = c.done || 0, failed = c.failed || 0, pending = c.pending || 0, cancelled = c.cancelled || 0;
  const running = c.running || 0;
  const total = c.total || done + failed + pending + cancelled;
  const settled = batchSettled(j);
  const bar = $("batch-progress");
  bar.max = Math.max(1, total);
  bar.value = done + failed + cancelled;
  const state = j.status === "cancelled" && !settled
    ? `cancelling (${running} running item${running === 1 ? "" : "s"} stopping)`
    : j.status === "done" ? "finished" : j.status;
  let s = `Batch ${j.id}: ${state}. ${done} done, ${failed} failed, ${pending} pending` +
    (cancelled ? `, ${cancelled} cancelled` : "") + ` of ${total}.`;
  if (typeof j.rate === "number" && j.rate > 0) s += ` ${fmt(j.rate, 1)} images per minute.`;
  if (!settled && j.status !== "cancelled" && typeof j.eta_s === "number" && j.eta_s > 0) {
    s += ` About ${Math.ceil(j.eta_s)} s left.`;
  } else if (settled && typeof j.elapsed_s === "number") {
    s += ` Took ${fmt(j.elapsed_s, j.elapsed_s < 10 ? 1 : 0)} s.`;
  }
  if (j.runner_error) s += ` Waiting: ${j.runner_error}.`;
  for (const w of j.warnings || []) s += ` Warning: ${pageWords(String(w))}.`;
  $("batch-status").textContent = s;
  const tbody = $("batch-table").tBodies[0];
  tbody.textContent = "";
  (j.items || []).forEach((item, i) => {
    const tr = tbody.insertRow();
    tr.className = `item-${item.status}`;
    tr.insertCell().textContent = item.name;
    tr.insertCell().textContent = item.status;
    const il = item.illuminant || {};
    tr.insertCell().textContent = (typeof il.cct === "number") ? `${Math.round(il.cct)} K` : "";
    const res = tr.insertCell();
    if (item.error) {
      const e = item.error;
      res.textContent = typeof e === "string" ? e : `${ERROR_WORDS[e.error] || e.error || "failed"}: ${e.detail || ""}`;
      res.className = "error-text";
    } else if (item.status === "done") {
      res.appendChild(itemLink(j.id, item, i));
      if (il.low_confidence) {
        const flag = document.createElement("span");
        flag.className = "low-confidence";
        flag.textContent = " low confidence: check this white balance";
        flag.title = `confidence ${fmt(100 * il.confidence, 0)} % (probability of an error under 3 degrees)`;
        res.appendChild(flag);
      }
    }
  });
  const zip = $("batch-zip");
  zip.hidden = !(settled && done > 0);
  zip.href = `/v1/batches/${encodeURIComponent(j.id)}/zip`;
  const cancel = $("batch-cancel");
  cancel.hidden = settled;
  cancel.disabled = j.status === "cancelled";
  cancel.textContent = j.status === "cancelled" ? "Cancelling…" : "Cancel";
  return settled;
}

// Polls until the batch is settled (not merely "cancelled": its running items
// still answer after that, and the counts change until they have).
async function poll() {
  if (!batch) return;
  const mine = batch;
  mine.timer = null;
  try {
    const resp = await fetch(`/v1/batches/${encodeURIComponent(mine.id)}`);
    if (!resp.ok) throw await failure(resp);
    const j = await resp.json();
    if (batch !== mine) return;   // another batch was started meanwhile
    const settled = renderBatch(j);
    if (!settled) mine.timer = setTimeout(poll, 500);
    else { $("batch-run").disabled = batchFiles.length === 0; }
  } catch (err) {
    showError($("batch-error"), err);
    $("batch-run").disabled = batchFiles.length === 0;
  }
}

async function startBatch() {
  if (!batchFiles.length) return;
  if (batch && batch.timer) clearTimeout(batch.timer);
  $("batch-error").hidden = true;
  $("batch-run").disabled = true;
  const fd = new FormData();
  for (const f of batchFiles) fd.append("files", f, f.name);
  const o = options();
  for (const [k, v] of Object.entries(o)) fd.append(k, v);
  fd.append("lighting", $("batch-lighting").value);
  try {
    let resp;
    try {
      resp = await fetch("/v1/batches", {method: "POST", body: fd});
    } catch (e) {
      throw new Error(`Could not reach the service (${e.message}).`);
    }
    if (resp.status === 404 || resp.status === 405) {
      throw new Error("Batch processing is not available on this server (POST /v1/batches is not there).");
    }
    if (!resp.ok) throw await failure(resp);
    const j = await resp.json();
    if (batch && batch.timer) clearTimeout(batch.timer);
    batch = {id: j.id, timer: null};
    $("batch-view").hidden = false;
    renderBatch(Object.assign({status: "queued", counts: {done: 0, failed: 0, pending: batchFiles.length},
      items: batchFiles.map((f) => ({name: f.name, status: "pending"}))}, j));
    poll();
  } catch (err) {
    showError($("batch-error"), err);
    $("batch-run").disabled = false;
  }
}

async function cancelBatch() {
  if (!batch) return;
  const mine = batch;
  $("batch-cancel").disabled = true;
  $("batch-cancel").textContent = "Cancelling…";
  try {
    const resp = await fetch(`/v1/batches/${encodeURIComponent(mine.id)}`, {method: "DELETE"});
    if (!resp.ok) throw await failure(resp);
    if (batch === mine && !renderBatch(await resp.json()) && mine.timer === null) poll();
  } catch (err) {
    showError($("batch-error"), err);
    $("batch-cancel").disabled = false;
    $("batch-cancel").textContent = "Cancel";
  }
}

// ---------------------------------------------------------------- wiring

// A drop zone: files dropped on it, or its file chooser opened by a click
// anywhere on it or, focused, by Enter or Space (its <input type=file> is
// hidden, so the zone is the keyboard's way in).
function dropZone(zone, input, onFiles) {
  zone.addEventListener("keydown", (e) => {
    if (e.target === zone && (e.key === "Enter" || e.key === " ")) { e.preventDefault(); input.click(); }
  });
  zone.addEventListener("click", (e) => {
    if (!e.target.closest("label, input, button, a")) input.click();
  });
  zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (e) => {
    e.preventDefault();
    zone.classList.remove("over");
    if (e.dataTransfer && e.dataTransfer.files.length) onFiles(e.dataTransfer.files);
  });
}

document.addEventListener("DOMContentLoaded", () => {
  loadOptions();
  // the options form never submits (Enter in a field would reload the page); a
  // listener, not an inline onsubmit, which the page's Content-Security-Policy refuses
  $("options").addEventListener("submit", (e) => e.preventDefault());
  $("file").addEventListener("change", (e) => chooseFile(e.target.files[0]));
  dropZone($("drop"), $("file"), (files) => chooseFile(files[0]));
  $("run").addEventListener("click", run);
  for (const id of ["img-original", "img-corrected"]) $(id).addEventListener("click", (e) => neutralFromClick($(id), e));
  $("neutral-clear").addEventListener("click", () => { if (current) { current.neutral = null; run(); } });
  $("dl-tiff").addEventListener("click", () => downloadCorrected("tiff", "tif"));
  $("dl-png").addEventListener("click", () => downloadCorrected("png", "png"));
  $("dl-json").addEventListener("click", downloadEstimate);
  $("dl-asshot").addEventListener("click", () => downloadCorrected("png", "png", "as-shot"));
  $("dl-xmp").addEventListener("click", () => downloadCorrected("xmp", "xmp"));
  $("batch-files").addEventListener("change", (e) => chooseBatch(e.target.files));
  dropZone($("batch-drop"), $("batch-files"), chooseBatch);
  $("batch-run").addEventListener("click", startBatch);
  $("batch-cancel").addEventListener("click", cancelBatch);
});
