// The web page's behaviour: plain JavaScript, no libraries, talks only to
// this service (same origin). One file: /v1/analyze (estimate, spectrum,
// diagnostics, light map), /v1/preview (before: the camera's as-shot white,
// after: the chosen white, downsized; re-rendered when the white changes),
// /v1/white-balance (the full-size images at 100 %, and downloads). Batch:
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
  const err = (body && typeof body.error === "string")
    ? new ApiError(resp.status, body.error, typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail))
    : new ApiError(resp.status, "http_error", resp.statusText || "no explanation given");
  err.retryAfter = Number(resp.headers.get("Retry-After")) || 0;   // seconds, with a 503 or 429
  return err;
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
  // "Daylight at…" / "Blackbody at…": the API's D<kelvin> and BB<kelvin>
  if (o.target === "custom-D" || o.target === "custom-BB") {
    o.target = `${o.target === "custom-D" ? "D" : "BB"}${Math.round(Number($("target-k").value) || 0)}`;
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
    img.blob = blob;   // the bytes shown (what the browser tests compare with the API's)
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
    const listed = new Set(Array.from($("opt-target").options, (o) => o.value));
    const more = $("opt-target-more");
    for (const name of models.illuminants || []) {
      if (!listed.has(name)) more.appendChild(new Option(name, name));
    }
    const camera = $("opt-camera");
    for (const c of cameras.cameras || []) camera.add(new Option(`${c.name} (measured)`, c.name));
  } catch (e) {
    // the defaults in the HTML still work
  }
}

// ---------------------------------------------------------------- words

// Confidence as words: the API's confidence is the probability that the
// estimate is within 3 degrees of the true light (calibrated on held-out
// benchmarks), its low_confidence flag the service's own threshold.
function confidenceWords(d) {
  if (typeof d.confidence !== "number") return "";
  const low = d.low_confidence === undefined ? d.confidence < 0.4 : d.low_confidence;
  const level = low ? "low" : d.confidence >= 0.75 ? "high" : "moderate";
  const inTen = Math.round(10 * d.confidence);
  return `Confidence is ${level}: about ${inTen} in 10 estimates like this one are within 3° of the true light ` +
    `(a colour difference few people notice) (${fmt(100 * d.confidence, 0)} %).`;
}

function isLowConfidence(d) {
  if (typeof d.confidence !== "number") return false;
  return d.low_confidence === undefined ? d.confidence < 0.4 : !!d.low_confidence;
}

function tt(t, tint) {
  return (typeof t === "number" && typeof tint === "number")
    ? `${Math.round(t)} K, tint ${tint >= 0 ? "+" : ""}${Math.round(tint)}` : "–";
}

let approxNoteShown = false;   // the "camera not measured" note is said once per visit, then only in the details

function diagnosticsInWords(j) {
  const d = j.diagnostics || {};
  const il = j.illuminant || {};
  const method = j.method || d.method || "unknown";
  let summary;
  if (method === "neutral-surface") {
    const picks = j.neutral && j.neutral.picks ? j.neutral.picks.length : 1;
    summary = picks > 1
      ? `The white is the mean of the ${picks} surfaces you clicked (each weighs the same).`
      : "The white was taken from the surface you clicked (its mean colour is used as the light).";
  } else {
    const what = typeof il.temperature === "number" ? `a light of about ${Math.round(il.temperature)} K` : "the light";
    summary = `Auto found ${what}, estimated by ${METHOD_WORDS[method] || method}.`;
  }
  const conf = confidenceWords(d);
  if (conf) summary += " " + conf;

  const cam = j.camera || {};
  const low = isLowConfidence(d);
  const notes = [], warnings = [], details = [];
  const approximate = cam.approximate || cam.source === "matrix-derived" || cam.source === "generic";
  for (const w of j.warnings || []) {
    const text = String(w);
    if (/^approximate: /.test(text)) continue;          // said below, in words, as a note or a warning
    warnings.push(pageWords(text));
  }
  if (approximate) {
    const how = cam.source === "generic"
      ? "This camera is not known: its colour response is taken as the average of the measured cameras."
      : "This camera's colour response was not measured; it is derived from the colour matrix in the file " +
        "(usual for DNG files).";
    if (low) {
      warnings.unshift(`${how} With the low confidence above, check the white: compare with As shot, or click a ` +
        "white or grey surface.");
    } else if (cam.source === "generic") {
      notes.push(how);
    } else if (!approxNoteShown) {
      notes.push(how);
      approxNoteShown = true;
    }
  } else if (low) {
    warnings.unshift("The estimate is uncertain: compare with As shot, or click a white or grey surface.");
  }
  if (j.as_shot && typeof j.as_shot.angle_to_estimate_deg === "number" && !warnings.some((w) => /as-shot|As shot/.test(w))) {
    notes.push(`The camera's own white (As shot) is ${fmt(j.as_shot.angle_to_estimate_deg, 1)}° from ` +
      (method === "neutral-surface" ? "the white you picked." : "Auto's."));
  }

  // the jargon, folded
  if (cam.name) details.push(`Camera: ${cam.name}, with ${SOURCE_WORDS[cam.source] || cam.source}.`);
  for (const n of cam.notes || []) details.push(`Camera model: ${n}.`);
  const why = d.decided_by || (typeof d.decision === "string" ? d.decision : "");
  if (why) details.push(`Decision: ${why}.`);
  if (d.confidence_rule) details.push(`Confidence rule: ${d.confidence_rule}.`);
  if (typeof d.pixels_used === "number" && typeof d.pixels_total === "number") {
    let s = `It used ${d.pixels_used.toLocaleString("en")} of ${d.pixels_total.toLocaleString("en")} analysis pixels`;
    // every pixel left out, by why, adding up to total - used (the rest: masked by the loader, a clipped
    // raw sample in their block, or unusable to the estimator)
    const why = typeof d.pixels_dark_or_saturated === "number" ? [[d.pixels_dark_or_saturated, "dark or saturated"]]
      : [[d.pixels_dark || 0, "dark"], [d.pixels_saturated || 0, "saturated"]];
    why.push([d.pixels_nonfinite || 0, "not finite"]);
    why.push([d.pixels_total - d.pixels_used - why.reduce((a, [k]) => a + k, 0), "masked (a clipped raw sample nearby)"]);
    const parts = why.filter(([k]) => k > 0).map(([k, w]) => `${k.toLocaleString("en")} ${w}`);
    if (parts.length) s += `; left out: ${parts.join(", ")}`;
    details.push(s + ".");
  }
  if (typeof d.posterior_spread_deg === "number") {
    details.push(`The probable lights lie within about ${fmt(d.posterior_spread_deg, 1)}° of each other ` +
      "(angle between camera responses).");
  }
  if (typeof d.region90_deg === "number") details.push(`90 % region of the estimate: ${fmt(d.region90_deg, 1)}°.`);
  if (typeof d.generic_vs_matrix_deg === "number") {
    details.push(`With the generic camera, the estimate is ${fmt(d.generic_vs_matrix_deg, 1)}° from the one made ` +
      `with the file's colour matrix; the confidence was multiplied by ${fmt(d.confidence_factor_generic, 2)}.`);
  }
  if (d.spectrum_rule) details.push(`Spectrum: ${d.spectrum_rule}.`);
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
  if (d.spatial_decision) details.push(`Several lights: ${d.spatial_decision} (${d.spatial_reason || "no reason given"}).`);
  if (j.as_shot && typeof j.as_shot.angle_to_estimate_deg === "number") {
    details.push(`The camera's own as-shot white balance is ${fmt(j.as_shot.angle_to_estimate_deg, 1)}° ` +
      "from this estimate (angle between camera responses).");
  }
  return {summary, notes, warnings, details};
}

// The server's warnings name API parameters; on the page they are clicks and buttons.
function pageWords(w) {
  return w.replace("use a white surface ('neutral') or white=as-shot",
    "click a white or grey surface in the picture, or choose As shot")
    .replace(/spatial='map' asks for a light map/, "\"always map the light\" under Options asks for a map");
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

// ---------------------------------------------------------------- white as Temperature/Tint

// Robertson's isotemperature lines as the DNG SDK tabulates them (reciprocal
// megakelvin, CIE 1960 u, v, slope): the same table as recovery/dng_color.py,
// so the page's Temperature/Tint is Camera Raw's and the API's.
const ROBERTSON = [
  [0, 0.18006, 0.26352, -0.24341], [10, 0.18066, 0.26589, -0.25479], [20, 0.18133, 0.26846, -0.26876],
  [30, 0.18208, 0.27119, -0.28539], [40, 0.18293, 0.27407, -0.30470], [50, 0.18388, 0.27709, -0.32675],
  [60, 0.18494, 0.28021, -0.35156], [70, 0.18611, 0.28342, -0.37915], [80, 0.18740, 0.28668, -0.40955],
  [90, 0.18880, 0.28997, -0.44278], [100, 0.19032, 0.29326, -0.47888], [125, 0.19462, 0.30141, -0.58204],
  [150, 0.19962, 0.30921, -0.70471], [175, 0.20525, 0.31647, -0.84901], [200, 0.21142, 0.32312, -1.0182],
  [225, 0.21807, 0.32909, -1.2168], [250, 0.22511, 0.33439, -1.4512], [275, 0.23247, 0.33904, -1.7298],
  [300, 0.24010, 0.34308, -2.0637], [325, 0.24702, 0.34655, -2.4681], [350, 0.25591, 0.34951, -2.9641],
  [375, 0.26400, 0.35200, -3.5814], [400, 0.27218, 0.35407, -4.3633], [425, 0.28039, 0.35577, -5.3762],
  [450, 0.28863, 0.35714, -6.7262], [475, 0.29685, 0.35823, -8.5955], [500, 0.30505, 0.35907, -11.324],
  [525, 0.31320, 0.35968, -15.628], [550, 0.32129, 0.36011, -23.325], [575, 0.32931, 0.36038, -40.770],
  [600, 0.33724, 0.36051, -116.45]];

// xy of a Temperature/Tint (DNG SDK dng_temperature::Get_xy_coord)
function ttToXy(temperature, tint) {
  const r = 1e6 / temperature, off = tint / -3000;
  let i = 0;
  while (i < ROBERTSON.length - 2 && ROBERTSON[i + 1][0] <= r) i++;
  const a = ROBERTSON[i], b = ROBERTSON[i + 1];
  const f = (b[0] - r) / (b[0] - a[0]);
  let u = a[1] * f + b[1] * (1 - f), v = a[2] * f + b[2] * (1 - f);
  const n1 = Math.hypot(1, a[3]), n2 = Math.hypot(1, b[3]);
  let du = f / n1 + (1 - f) / n2, dv = f * a[3] / n1 + (1 - f) * b[3] / n2;
  const n = Math.hypot(du, dv);
  u += du / n * off; v += dv / n * off;
  const den = u - 4 * v + 2;
  return [1.5 * u / den, v / den];
}

// The slider's 0..1000 is linear in mireds (even steps of perceived colour), 2000 K to 50000 K.
const MIRED_WARM = 1e6 / 2000, MIRED_COOL = 1e6 / 50000;
const sliderToK = (v) => 1e6 / (MIRED_WARM - v / 1000 * (MIRED_WARM - MIRED_COOL));
const kToSlider = (k) => Math.round(1000 * (MIRED_WARM - 1e6 / k) / (MIRED_WARM - MIRED_COOL));

// While a slider moves, the corrected image is changed in the browser at once
// (a von Kries adaptation in Bradford cone space from the white it was rendered
// for to the slider's, applied in linear sRGB by an SVG colour-matrix filter);
// the exact image from the service replaces it a moment later.
const BRADFORD = [[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]];
const SRGB_TO_XYZ = [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]];
const mul = (A, B) => A.map((row) => B[0].map((_, j) => row.reduce((s, a, k) => s + a * B[k][j], 0)));
const mulv = (A, v) => A.map((row) => row.reduce((s, a, k) => s + a * v[k], 0));
function inv3(m) {
  const [[a, b, c], [d, e, f], [g, h, i]] = m;
  const A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
  const det = a * A + b * B + c * C;
  return [[A / det, -(b * i - c * h) / det, (b * f - c * e) / det],
    [B / det, (a * i - c * g) / det, -(a * f - c * d) / det],
    [C / det, -(a * h - b * g) / det, (a * e - b * d) / det]];
}
function approxMatrix(from, to) {
  const xyz = ([x, y]) => [x / y, 1, (1 - x - y) / y];
  const l0 = mulv(BRADFORD, xyz(ttToXy(from.t, from.tint))), l1 = mulv(BRADFORD, xyz(ttToXy(to.t, to.tint)));
  const D = [[l0[0] / l1[0], 0, 0], [0, l0[1] / l1[1], 0], [0, 0, l0[2] / l1[2]]];
  const M = mul(inv3(SRGB_TO_XYZ), mul(inv3(BRADFORD), mul(D, mul(BRADFORD, SRGB_TO_XYZ))));
  const y = mulv(SRGB_TO_XYZ, mulv(M, [1, 1, 1]))[1];          // keep white's luminance
  return M.map((row) => row.map((v) => v / y));
}

// ---------------------------------------------------------------- one file

let current = null;   // {file, options, estimate, neutral, picks, box, hasAsShot, wb, shown, seq}
const view = {mode: "split", zoom: "fit", s: 1, tx: 0, ty: 0, split: 0.5, W: 0, H: 0, full: null};

function chooseFile(file) {
  current = file ? {file, wb: {mode: "auto"}, seq: 0, picks: []} : null;
  view.zoom = "fit";                       // a new picture starts whole
  $("file-name").textContent = file ? `${file.name} (${(file.size / 1e6).toFixed(2)} MB)` : "no file chosen";
  $("run").disabled = !file;
  if (file) run();
}

// The estimation options of every request about the one file (analysis, previews, downloads,
// surfaces), so the picture, the words and the downloads come from the same light (or light map).
function estimationFields(o) {
  const f = {};
  for (const k of ["camera", "method", "quality", "spatial"]) if (o[k]) f[k] = o[k];
  return f;
}

// The white field of /v1/preview and /v1/white-balance for the chosen mode.
function whiteField() {
  const wb = current.wb;
  if (wb.mode === "as-shot") return "as-shot";
  if (wb.mode === "custom") return `${Math.round(wb.t)}/${wb.tint >= 0 ? "+" : ""}${Math.round(wb.tint)}`;
  return "estimate";
}

function renderFields(white) {
  const o = current.options;
  const f = Object.assign(estimationFields(o), {target: o.target || "D65", white});
  if (white === "estimate" && current.neutral) f.neutral = JSON.stringify(current.neutral);
  return f;
}

function noteOf(resp) {
  try { return JSON.parse(resp.headers.get("X-Preview") || "{}"); } catch (e) { return {}; }
}

async function beforePreview(file) {
  // the camera's own white through the same rendering as After, so the split
  // compares whites only; a file without one: LibRaw's (or the unbalanced) rendering
  try {
    const r = await post("/v1/preview", formFor(file, Object.assign(estimationFields(current.options),
      {wb: "corrected", white: "as-shot", target: current.options.target || "D65", format: "jpeg", max_side: "1024"})));
    return {resp: r, asShot: true};
  } catch (err) {
    if (!(err instanceof ApiError) || err.code !== "no_as_shot_white") throw err;
  }
  const r = await post("/v1/preview", formFor(file, {wb: "camera", format: "jpeg", max_side: "1024"}));
  return {resp: r, asShot: false};
}

async function run() {
  if (!current) return;
  const file = current.file;
  const opts = options();
  if ($("opt-spatial").value) opts.spatial = $("opt-spatial").value;   // one file only (not a batch option)
  current.options = opts;
  current.seq++;
  view.full = null;
  $("error").hidden = true;
  $("surface").hidden = true;            // a surface read under the earlier settings
  $("run").disabled = true;
  $("status").textContent = `Analysing ${file.name}…`;
  const t0 = performance.now();
  const analyzeOpts = estimationFields(opts);
  if (current.neutral) analyzeOpts.neutral = JSON.stringify(current.neutral);
  if (current.wb.mode === "as-shot" && current.neutral) current.wb = {mode: "auto"};
  try {
    const [analysis, before, corrected] = await Promise.all([
      post("/v1/analyze", formFor(file, analyzeOpts)).then((r) => r.json()),
      beforePreview(file),
      post("/v1/preview", formFor(file, Object.assign(renderFields(whiteField()), {wb: "corrected", format: "jpeg",
        max_side: "1024"}))),
    ]);
    if (current === null || current.file !== file) return;   // another file was chosen meanwhile
    current.estimate = analysis;
    current.hasAsShot = before.asShot;
    const on = noteOf(before.resp), cn = noteOf(corrected);
    $("result").hidden = false;
    await Promise.all([setImage($("img-original"), await before.resp.blob()),
      setImage($("img-corrected"), await corrected.blob())]);
    $("before-what").textContent = before.asShot ? "the camera's own white (As shot), same rendering"
      : "the file as LibRaw shows it (it records no white of its own)";
    // the as-shot preview repeats the estimate's warnings (said below); LibRaw's rendering has its own
    const beforeWarnings = before.asShot ? [] : (on.warnings || []);
    $("original-note").textContent = beforeWarnings.length ? ` (${beforeWarnings.join("; ")})` : "";
    $("corrected-target").textContent = targetWords(opts.target);
    const outW = cn.output_width || cn.width, outH = cn.output_height || cn.height;
    $("corrected-note").textContent = `(preview ${cn.width}×${cn.height}; the downloads are ${outW}×${outH})`;
    current.box = {full: [cn.full_height || outH, cn.full_width || outW], crop: cn.crop || [0, 0, outH, outW]};
    view.W = outW; view.H = outH;
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
    fillList($("diag-warnings"), words.warnings, "Check: ");
    fillList($("diag-notes"), words.notes, "");
    fillList($("diag-details"), words.details, "");
    showLights(analysis);
    showWhiteBalance();
    current.shown = shownWhite(whiteField());
    layout(true);
    afterChanged();
    if (view.zoom !== "fit") loadFull();   // zoomed in: the full-size images for the new settings
    $("status").textContent = `Done in ${((performance.now() - t0) / 1000).toFixed(1)} s.`;
  } catch (err) {
    $("status").textContent = "";
    if (current && current.file === file && !current.estimate) $("result").hidden = true;   // nothing of this file to show
    showError($("error"), err);
  } finally {
    $("run").disabled = !current;
  }
}

function fillList(ul, items, prefix) {
  ul.textContent = "";
  for (const s of items) { const li = document.createElement("li"); li.textContent = prefix + s; ul.appendChild(li); }
}

function targetWords(t) {
  if (!t || t === "D65") return "D65 (daylight)";
  if (t === "estimate" || t === "as-seen") return "the scene's own light (as seen)";
  return t;
}

// ---- white balance: As shot / Auto / Custom

// The Temperature/Tint of a white field, as far as the page knows it.
function shownWhite(white) {
  const a = current.estimate || {};
  if (white === "as-shot") return a.as_shot && typeof a.as_shot.temperature === "number"
    ? {t: a.as_shot.temperature, tint: a.as_shot.tint} : null;
  if (white === "estimate") {
    const il = a.illuminant || {};
    return typeof il.temperature === "number" ? {t: il.temperature, tint: il.tint} : null;
  }
  const [t, tint] = white.split("/").map(Number);
  return {t, tint};
}

function showWhiteBalance() {
  const a = current.estimate || {};
  const il = a.illuminant || {}, as = a.as_shot || {};
  const asTxt = typeof as.temperature === "number" ? tt(as.temperature, as.tint) : (current.hasAsShot ? "recorded (no temperature)" : "not recorded in the file");
  const ang = typeof as.angle_to_estimate_deg === "number" ? ` (${fmt(as.angle_to_estimate_deg, 1)}° from Auto)` : "";
  $("asshot-tt").textContent = asTxt + (typeof as.temperature === "number" ? ang : "");
  $("auto-tt").textContent = tt(il.temperature, il.tint) + (current.neutral ? " (your white)" : "");
  $("wb-asshot").disabled = !current.hasAsShot;
  for (const [id, m] of [["wb-asshot", "as-shot"], ["wb-auto", "auto"], ["wb-custom", "custom"]]) {
    $(id).setAttribute("aria-pressed", String(current.wb.mode === m));
  }
  const w = current.wb.mode === "custom" ? current.wb : shownWhite(whiteField());
  if (w) {
    $("temp").value = kToSlider(w.t);
    $("tint").value = Math.round(w.tint);
  }
  $("temp-value").textContent = w ? `${Math.round(w.t)} K` : "–";
  $("tint-value").textContent = w ? `${w.tint >= 0 ? "+" : ""}${Math.round(w.tint)}` : "–";
  const nPicks = current.picks.length;
  $("dl-white").textContent = current.wb.mode === "custom" ? `Custom ${whiteField()}`
    : current.wb.mode === "as-shot" ? "As shot"
    : (current.neutral ? (nPicks > 1 ? `the mean of your ${nPicks} picks` : "your white") : "Auto");
}

function setWhiteMode(mode) {
  if (!current || !current.estimate) return;
  if (mode === "custom") {
    const w = current.wb.mode === "custom" ? current.wb : (shownWhite(whiteField()) || {t: 5500, tint: 0});
    current.wb = {mode, t: w.t, tint: w.tint};
  } else {
    current.wb = {mode};
  }
  showWhiteBalance();
  rerenderAfter();
}

let sliderTimer = null;
function onSlider() {
  if (!current || !current.estimate) return;
  const t = sliderToK(Number($("temp").value)), tint = Number($("tint").value);
  current.wb = {mode: "custom", t, tint};
  showWhiteBalance();
  // at once: the browser's approximation; then the service's exact rendering
  if (current.shown) {
    const M = approxMatrix(current.shown, {t, tint});
    $("wb-approx-matrix").setAttribute("values",
      M.map((r) => `${r.map((v) => v.toFixed(5)).join(" ")} 0 0`).join("  ") + "  0 0 0 1 0");
    $("img-corrected").style.filter = "url(#wb-approx)";
  }
  $("wb-status").textContent = "Rendering…";
  clearTimeout(sliderTimer);
  sliderTimer = setTimeout(rerenderAfter, 250);
}

// The corrected image again for the chosen white (the preview; at 100 % also the full-size image).
async function rerenderAfter() {
  if (!current || !current.estimate) return;
  const file = current.file, seq = ++current.seq, white = whiteField();
  $("wb-status").textContent = "Rendering…";
  try {
    const r = await post("/v1/preview", formFor(file, Object.assign(renderFields(white),
      {wb: "corrected", format: "jpeg", max_side: "1024"})));
    const blob = await r.blob();
    if (!current || current.seq !== seq) return;
    view.full = view.full && view.full.before ? {before: view.full.before} : null;
    await setImage($("img-corrected"), blob);
    $("img-corrected").style.filter = "";
    current.shown = shownWhite(white);
    $("wb-status").textContent = "";
    afterChanged();
    if (view.zoom !== "fit") loadFull();
  } catch (err) {
    if (current && current.seq === seq) {
      $("wb-status").textContent = "";
      $("img-corrected").style.filter = "";
      showError($("error"), err);
    }
  }
}

// ---- the view: split, zoom, pan, pick

function viewerSize() {
  const v = $("viewer");
  return [v.clientWidth, v.clientHeight];
}

function fitScale() {
  const [vw, vh] = viewerSize();
  return Math.min(vw / view.W, vh / view.H);
}

// Size the viewer to the picture (at most 75 % of the window's height) and place the stage.
function layout(reset) {
  if (!view.W) return;
  viewerHeight();
  const [vw, vh] = viewerSize();
  if (view.zoom === "fit" || reset) {
    if (view.zoom === "fit") {
      view.s = fitScale();
      view.tx = (vw - view.W * view.s) / 2;
      view.ty = (vh - view.H * view.s) / 2;
    }
  }
  clampPan();
  applyView();
}

// The viewer is as tall as the picture at Fit (at most 75 % of the window);
// zoomed in, at least 60 % of the window (a phone's fitted picture is a strip).
function viewerHeight() {
  const v = $("viewer");
  let want = Math.min(v.clientWidth * view.H / view.W, 0.75 * window.innerHeight);
  if (view.zoom !== "fit") want = Math.max(want, 0.6 * window.innerHeight);
  v.style.height = `${Math.max(160, Math.round(want))}px`;
}

function clampPan() {
  const [vw, vh] = viewerSize();
  const w = view.W * view.s, h = view.H * view.s;
  view.tx = w <= vw ? (vw - w) / 2 : Math.min(0, Math.max(vw - w, view.tx));
  view.ty = h <= vh ? (vh - h) / 2 : Math.min(0, Math.max(vh - h, view.ty));
}

function applyView() {
  const stage = $("stage");
  stage.style.width = `${view.W}px`;
  stage.style.height = `${view.H}px`;
  stage.style.transform = `translate(${view.tx}px, ${view.ty}px) scale(${view.s})`;
  const [vw] = viewerSize();
  const divider = $("divider");
  divider.hidden = view.mode !== "split";
  divider.style.left = `${view.split * vw}px`;
  divider.setAttribute("aria-valuenow", String(Math.round(view.split * 100)));
  let cut = 0;   // the after layer shows right of this fraction of the stage
  if (view.mode === "split") cut = Math.min(1, Math.max(0, (view.split * vw - view.tx) / (view.s * view.W)));
  $("after-layer").hidden = view.mode === "before";
  $("after-layer").style.clipPath = `inset(0 0 0 ${(100 * cut).toFixed(3)}%)`;
  $("img-original").hidden = view.mode === "after";
  drawMarks();
  $("viewer").classList.toggle("zoomed", view.zoom !== "fit");
  for (const [id, m] of [["view-split", "split"], ["view-before", "before"], ["view-after", "after"]]) {
    $(id).setAttribute("aria-pressed", String(view.mode === m));
  }
  $("zoom-fit").setAttribute("aria-pressed", String(view.zoom === "fit"));
  $("zoom-100").setAttribute("aria-pressed", String(view.zoom === "100"));
}

function setMode(mode) { view.mode = mode; applyView(); }

// 100 %: one pixel of the download per device pixel, centred on the picked white or the view's centre.
function setZoom(zoom) {
  if (!view.W) return;
  const [vw, vh] = viewerSize();
  const last = current && current.picks.length ? current.picks[current.picks.length - 1] : null;
  const cx = last ? last.x : (vw / 2 - view.tx) / view.s;
  const cy = last ? last.y : (vh / 2 - view.ty) / view.s;
  view.zoom = zoom;
  viewerHeight();
  if (zoom === "100") {
    view.s = 1 / (window.devicePixelRatio || 1);
    view.tx = vw / 2 - cx * view.s;
    view.ty = vh / 2 - cy * view.s;
    clampPan();
    applyView();
    loadFull();
  } else {
    layout();
    $("zoom-note").textContent = "";
  }
}

// Zoom to scale s (between Fit and 400 %) keeping the picture's point under (x, y) where it is
// (or bringing the picture's point ``anchor`` there: a pinch's fingers pan as they zoom).
function zoomAt(s, x, y, anchor) {
  if (!view.W) return;
  const dpr = window.devicePixelRatio || 1, fit = fitScale();
  s = Math.min(4 / dpr, Math.max(fit, s));
  const [px, py] = anchor || [(x - view.tx) / view.s, (y - view.ty) / view.s];
  view.s = s;
  view.tx = x - px * s;
  view.ty = y - py * s;
  view.zoom = Math.abs(s - fit) < 1e-3 * fit ? "fit" : Math.abs(s * dpr - 1) < 0.02 ? "100" : "free";
  if (view.zoom === "100") view.s = 1 / dpr;
  viewerHeight();     // the viewer's top stays: the point under (x, y) too
  if (view.zoom === "fit") {
    layout();
    $("zoom-note").textContent = "";
    return;
  }
  clampPan();
  applyView();
  loadFull();
}

function zoomWords() {
  return `${Math.round(100 * view.s * (window.devicePixelRatio || 1))} %: full size`;
}

// The full-size images for 100 %: the download's own rendering (POST /v1/white-balance, JPEG).
async function loadFull() {
  if (!current || !current.estimate) return;
  const white = whiteField(), seq = current.seq, file = current.file;
  const want = {after: JSON.stringify(renderFields(white)), before: current.hasAsShot};
  const full = view.full || {};
  const jobs = [];
  if (full.after !== want.after) jobs.push(["after", white]);
  if (current.hasAsShot && !full.before) jobs.push(["before", "as-shot"]);
  if (!jobs.length) { $("zoom-note").textContent = zoomWords(); return; }
  $("zoom-note").textContent = "Loading the full-size image…";
  try {
    const blobs = await Promise.all(jobs.map(([, w]) => post("/v1/white-balance",
      formFor(file, Object.assign(renderFields(w), {format: "jpeg"}))).then((r) => r.blob())));
    if (!current || current.seq !== seq) return;
    view.full = Object.assign({}, view.full);
    for (let i = 0; i < jobs.length; i++) {
      const [which] = jobs[i];
      await setImage($(which === "after" ? "img-corrected" : "img-original"), blobs[i]);
      view.full[which] = which === "after" ? want.after : true;
    }
    if (jobs.some(([w]) => w === "after")) afterChanged();
    $("zoom-note").textContent = view.zoom !== "fit" ? zoomWords() : "";
  } catch (err) {
    $("zoom-note").textContent = "";
    showError($("error"), err);
  }
}

function viewerPoint(ev) {
  const box = $("viewer").getBoundingClientRect();
  return [ev.clientX - box.left, ev.clientY - box.top];
}

function wireViewer() {
  const v = $("viewer");
  let drag = null;
  // two fingers: pinch to zoom; the picture's point under the fingers'
  // midpoint when they landed stays under their midpoint (zoom and pan
  // together, as a phone's photo viewer does); no pick. A finger that lands
  // on the split's divider counts too: the pinch wins and the divider goes
  // back to where it was.
  const touches = new Map();
  let pinch = null;
  let dividerDrag = null;   // {id, split}: the divider follows this pointer
  v.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0) return;
    const onDivider = Boolean(ev.target.closest("#divider"));
    if (onDivider && ev.pointerType !== "touch") return;
    const [x, y] = viewerPoint(ev);
    touches.set(ev.pointerId, [x, y]);
    if (touches.size === 2) {
      const [a, b] = [...touches.values()];
      const mx = (a[0] + b[0]) / 2, my = (a[1] + b[1]) / 2;
      pinch = {d: Math.hypot(a[0] - b[0], a[1] - b[1]) || 1, s: view.s,
               anchor: [(mx - view.tx) / view.s, (my - view.ty) / view.s]};
      drag = null;
      if (dividerDrag) { view.split = dividerDrag.split; dividerDrag = null; applyView(); }
      return;
    }
    if (onDivider) return;               // one finger on the divider moves the divider
    drag = {x, y, tx: view.tx, ty: view.ty, moved: false, id: ev.pointerId};
    if (view.zoom !== "fit") v.setPointerCapture(ev.pointerId);
  });
  v.addEventListener("pointermove", (ev) => {
    if (touches.has(ev.pointerId)) touches.set(ev.pointerId, viewerPoint(ev));
    if (pinch && touches.size === 2) {
      const [a, b] = [...touches.values()];
      zoomAt(pinch.s * Math.hypot(a[0] - b[0], a[1] - b[1]) / pinch.d, (a[0] + b[0]) / 2, (a[1] + b[1]) / 2,
             pinch.anchor);
      return;
    }
    if (!drag || drag.id !== ev.pointerId) return;
    const [x, y] = viewerPoint(ev);
    if (Math.hypot(x - drag.x, y - drag.y) > 4) drag.moved = true;
    if (drag.moved && view.zoom !== "fit") {
      v.classList.add("panning");
      view.tx = drag.tx + x - drag.x;
      view.ty = drag.ty + y - drag.y;
      clampPan();
      applyView();
    }
  });
  const end = (ev) => {
    touches.delete(ev.pointerId);
    if (touches.size < 2) pinch = null;
    if (!drag || drag.id !== ev.pointerId) return;
    const d = drag;
    drag = null;
    v.classList.remove("panning");
    if (ev.type === "pointerup" && !d.moved) {
      if ($("pick-surface").checked) readSurface(d.x, d.y);
      else pickWhite(d.x, d.y, ev.shiftKey || $("pick-add").checked);
    }
  };
  v.addEventListener("pointerup", end);
  v.addEventListener("pointercancel", end);

  const div = $("divider");
  div.addEventListener("pointerdown", (ev) => {
    dividerDrag = {id: ev.pointerId, split: view.split};
    div.setPointerCapture(ev.pointerId);
    ev.preventDefault();
  });
  div.addEventListener("pointermove", (ev) => {
    if (!dividerDrag || dividerDrag.id !== ev.pointerId) return;
    const [x] = viewerPoint(ev);
    view.split = Math.min(1, Math.max(0, x / viewerSize()[0]));
    applyView();
  });
  div.addEventListener("pointerup", () => { dividerDrag = null; });
  div.addEventListener("pointercancel", () => { dividerDrag = null; });
  div.addEventListener("keydown", (ev) => {
    const step = {ArrowLeft: -0.05, ArrowRight: 0.05, Home: -1, End: 1}[ev.key];
    if (step === undefined) return;
    ev.preventDefault();
    view.split = Math.min(1, Math.max(0, view.split + step));
    applyView();
  });
  v.addEventListener("keydown", (ev) => {
    if (ev.target !== v || view.zoom === "fit") return;
    const d = {ArrowLeft: [40, 0], ArrowRight: [-40, 0], ArrowUp: [0, 40], ArrowDown: [0, -40]}[ev.key];
    if (!d) return;
    ev.preventDefault();
    view.tx += d[0]; view.ty += d[1];
    clampPan(); applyView();
  });
  // Ctrl + wheel (and a trackpad's pinch, which browsers send so) zooms about the pointer
  v.addEventListener("wheel", (ev) => {
    if (!(ev.ctrlKey || ev.metaKey) || !view.W) return;
    ev.preventDefault();
    const [x, y] = viewerPoint(ev);
    zoomAt(view.s * Math.exp(-ev.deltaY * 0.002), x, y);
  }, {passive: false});
  window.addEventListener("resize", () => { if (view.W) layout(); });
}

// "Use this as white": a click fixes the light from a small square around
// that point (about 1 % of the long side), in the decoded image's pixels.
// With Shift (or "Average several picks") the click adds a pick: the API
// averages them (neutral = a list of squares: the mean of each pick's white,
// each weighing the same), so the page, the downloads and the REST API agree.
const MAX_PICKS = 16;   // the API's limit (service.options.MAX_NEUTRAL_PICKS)
function pickWhite(x, y, add) {
  if (!current || !current.box || !view.W) return;
  const px = (x - view.tx) / view.s, py = (y - view.ty) / view.s;
  if (px < 0 || py < 0 || px >= view.W || py >= view.H) return;
  const [H, W] = current.box.full, [top, left] = current.box.crop;
  const r = Math.min(H - 1, top + Math.floor(py)), c = Math.min(W - 1, left + Math.floor(px));
  const half = Math.max(2, Math.round(0.005 * Math.max(W, H)));
  const neutral = [Math.max(0, r - half), Math.max(0, c - half), Math.min(H, r + half + 1), Math.min(W, c + half + 1)];
  const pick = {x: px, y: py, neutral};
  if (add && current.picks.length && current.neutral) {
    if (current.picks.length >= MAX_PICKS) {
      $("neutral-note").textContent = `At most ${MAX_PICKS} picks: click without Shift to start again.`;
      return;
    }
    current.picks.push(pick);
  } else {
    current.picks = [pick];
  }
  current.neutral = current.picks.length > 1 ? current.picks.map((p) => p.neutral) : neutral;
  current.wb = {mode: "auto"};
  applyView();
  run();
}

// "Read a surface": a click asks /v1/surfaces for the reflectance of a small
// square there (the estimate of its mean camera response under Auto's light),
// drawn with its calibrated 90 % band and the one number that goes with it.
async function readSurface(x, y) {
  if (!current || !current.box || !view.W) return;
  const px = (x - view.tx) / view.s, py = (y - view.ty) / view.s;
  if (px < 0 || py < 0 || px >= view.W || py >= view.H) return;
  const [H, W] = current.box.full, [top, left] = current.box.crop;
  const r = Math.min(H - 1, top + Math.floor(py)), c = Math.min(W - 1, left + Math.floor(px));
  const half = Math.max(2, Math.round(0.005 * Math.max(W, H)));
  const rect = [Math.max(0, r - half), Math.max(0, c - half), Math.min(H, r + half + 1), Math.min(W, c + half + 1)];
  const seq = current.seq;
  $("surface").hidden = false;
  $("surface-words").textContent = "Reading the surface there…";
  // the same estimation fields as the picture (quality too), so the surface is read under the light shown
  const f = Object.assign(estimationFields(current.options), {rects: JSON.stringify([rect]), metamers: "true",
                                                          metamer_model: "measured"});
  try {
    const j = await post("/v1/surfaces", formFor(current.file, f)).then((resp) => resp.json());
    if (!current || current.seq !== seq) return;
    const s = j.surfaces[0];
    plotReflectance($("surface-plot"), j.wavelengths, s.reflectance, s.reflectance_std,
      s.metamer_lower && s.metamer_upper ? [s.metamer_lower, s.metamer_upper] : null);
    const where = `rows ${rect[0]}–${rect[2]}, columns ${rect[1]}–${rect[3]}`;
    const trust = typeof s.expected_rmse === "number"
      ? `Expected error ${fmt(s.expected_rmse, 3)} (RMS over wavelengths, reflectance 0–1). The shaded band ` +
        "is a 90 % band: at each wavelength it is calibrated to hold the true reflectance 90 % of the time " +
        "(on measured surfaces kept aside)."
      : "No band: the literal method (eq. 36) gives none.";
    const metamers = s.metamer_lower
      ? " The dashed outline is the metamer set of surfaces like measured ones: every such reflectance that " +
        "gives this colour under the light lies inside it (a model of 274 measured surfaces); where it is " +
        "wide the camera cannot tell, and the estimate there is what measured surfaces are like."
      : "";
    const warn = s.warnings.length ? ` Check: ${s.warnings.join("; ")}.` : "";
    const light = j.light_map ? "under the light the light map finds there" : "under Auto's light";
    $("surface-words").textContent = `Surface at ${where}, ${light}. ${trust}${metamers}${warn}`;
    $("surface-words").dataset.expectedRmse = String(s.expected_rmse);
    $("surface-words").dataset.rect = JSON.stringify(rect);
  } catch (err) {
    $("surface-words").textContent = "";
    showError($("error"), err);
  }
}

function plotReflectance(container, wl, mean, std, metamers = null) {
  container.textContent = "";
  const W = 320, H = 200, L = 40, R = 14, T = 8, B = 34, Z = 1.6448536269514722;
  const svg = el("svg", {viewBox: `0 0 ${W} ${H}`, width: "100%", role: "img", id: "surface-svg",
    "aria-label": "the surface's estimated reflectance with its 90 % band" +
      (metamers ? " and the range of its metamer set" : "")});
  const lo = mean.map((m, i) => (std ? m - Z * std[i] : m)), hi = mean.map((m, i) => (std ? m + Z * std[i] : m));
  const x0 = wl[0], x1 = wl[wl.length - 1];
  const tops = metamers ? hi.concat(metamers[1]) : hi;
  const ymax = Math.max(1, ...tops.filter(isFinite)), ymin = Math.min(0, ...lo.filter(isFinite));
  const sx = (x) => L + (x - x0) / (x1 - x0) * (W - L - R);
  const sy = (y) => T + (1 - (y - ymin) / (ymax - ymin)) * (H - T - B);
  svg.appendChild(el("line", {x1: L, y1: sy(ymin), x2: L, y2: T, class: "axis"}));
  svg.appendChild(el("line", {x1: L, y1: sy(0), x2: W - R, y2: sy(0), class: "axis"}));
  for (let x = Math.ceil(x0 / 50) * 50; x <= x1; x += 50) {
    svg.appendChild(el("text", {x: sx(x), y: sy(ymin) + 16, "text-anchor": "middle", class: "tick"}, `${x}`));
  }
  for (const y of [0, 0.5, 1]) {
    svg.appendChild(el("text", {x: L - 6, y: sy(y) + 4, "text-anchor": "end", class: "tick"}, y.toFixed(1)));
  }
  svg.appendChild(el("text", {x: (L + W - R) / 2, y: H - 4, "text-anchor": "middle", class: "label"},
    "wavelength (nm)"));
  const path = (ys) => ys.map((y, i) => `${i ? "L" : "M"}${sx(wl[i]).toFixed(1)},${sy(y).toFixed(1)}`).join(" ");
  const polygon = (a, b) => `${path(a)} ` + b.map((y, i) => [wl[i], y]).reverse()
    .map(([x, y]) => `L${sx(x).toFixed(1)},${sy(y).toFixed(1)}`).join(" ") + " Z";
  if (metamers) {
    svg.appendChild(el("path", {d: polygon(metamers[0], metamers[1]), id: "surface-metamers", class: "metamers"}));
  }
  if (std) {
    svg.appendChild(el("path", {d: polygon(lo, hi), id: "surface-band", class: "band"}));
  }
  svg.appendChild(el("path", {d: path(mean), id: "surface-mean", class: "curve"}));
  container.appendChild(svg);
}

function drawMarks() {
  const picks = current ? current.picks : [];
  const first = $("pick-mark");
  const marks = [first, ...document.querySelectorAll(".pick-mark.extra")];
  while (marks.length < picks.length) {
    const m = first.cloneNode(false);
    m.removeAttribute("id");
    m.classList.add("extra");
    first.parentNode.insertBefore(m, first.nextSibling);
    marks.push(m);
  }
  marks.forEach((m, i) => {
    const p = picks[i];
    m.hidden = !p;
    if (p) {
      m.style.left = `${view.tx + p.x * view.s}px`;
      m.style.top = `${view.ty + p.y * view.s}px`;
    }
  });
}

function showNeutral(analysis) {
  const n = analysis && analysis.neutral;
  $("neutral-clear").hidden = !current.neutral;
  const ang = n && typeof n.angle_to_estimate_deg === "number" ? `, ${fmt(n.angle_to_estimate_deg, 1)}° from Auto's` : "";
  if (n && n.picks) {
    $("neutral-note").textContent = `White averaged from ${n.picks.length} picks (each weighs the same; they ` +
      `differ from their mean by up to ${fmt(n.spread_deg, 1)}°${ang}). Shift-click to add another; click ` +
      "without Shift to start again.";
  } else if (n) {
    $("neutral-note").textContent = `White taken from the marked surface (rows ${n.where[0]}–${n.where[2]}, ` +
      `columns ${n.where[1]}–${n.where[3]}; ${n.cells_used} cells${ang}). Click elsewhere to change it.`;
  } else {
    $("neutral-note").textContent = "Click a white or grey surface in the picture to use it as white.";
  }
}

// ---- histogram and clipping (of the corrected image as shown)

const CLIP_HIGH = 254, CLIP_LOW = 1;   // 8-bit levels counted as clipped (JPEG leaves 255 and 0 a level of slack)

function imagePixels(img, maxPixels) {
  const w0 = img.naturalWidth, h0 = img.naturalHeight;
  const k = Math.min(1, Math.sqrt(maxPixels / (w0 * h0)));
  const w = Math.max(1, Math.round(w0 * k)), h = Math.max(1, Math.round(h0 * k));
  const c = document.createElement("canvas");
  c.width = w; c.height = h;
  const ctx = c.getContext("2d", {willReadFrequently: true});
  ctx.drawImage(img, 0, 0, w, h);
  return ctx.getImageData(0, 0, w, h);
}

function afterChanged() {
  const img = $("img-corrected");
  if (!img.naturalWidth) return;
  const data = imagePixels(img, 1.1e6).data;
  const counts = [new Array(256).fill(0), new Array(256).fill(0), new Array(256).fill(0)];
  let high = 0, low = 0;
  const n = data.length / 4;
  for (let i = 0; i < data.length; i += 4) {
    const r = data[i], g = data[i + 1], b = data[i + 2];
    counts[0][r]++; counts[1][g]++; counts[2][b]++;
    if (r >= CLIP_HIGH || g >= CLIP_HIGH || b >= CLIP_HIGH) high++;
    else if (r <= CLIP_LOW && g <= CLIP_LOW && b <= CLIP_LOW) low++;
  }
  drawHistogram(counts);
  const canvas = $("histogram");
  canvas.dataset.counts = JSON.stringify(counts);
  canvas.dataset.pixels = String(n);
  $("clip-stats").textContent = `Clipped highlights (a channel at ${CLIP_HIGH}–255): ${percent(high / n)}; ` +
    `crushed shadows (all channels at 0–${CLIP_LOW}): ${percent(low / n)}.`;
  $("clip-stats").dataset.high = String(high / n);
  if ($("show-clipping").checked) drawClipping();
}

function drawHistogram(counts) {
  const c = $("histogram"), ctx = c.getContext("2d");
  const W = c.width, H = c.height;
  ctx.globalCompositeOperation = "source-over";
  ctx.fillStyle = "#222";
  ctx.fillRect(0, 0, W, H);
  // scale to the tallest bin between the ends (the end bins hold the clipping, shown by the overlay)
  let top = 1;
  for (const ch of counts) for (let v = 1; v < 255; v++) top = Math.max(top, ch[v]);
  ctx.globalCompositeOperation = "lighter";
  const colours = ["rgba(230,60,60,0.9)", "rgba(60,200,60,0.9)", "rgba(70,110,255,0.9)"];
  counts.forEach((ch, k) => {
    ctx.fillStyle = colours[k];
    ctx.beginPath();
    ctx.moveTo(0, H);
    for (let v = 0; v < 256; v++) ctx.lineTo((v + 0.5) * W / 256, H - Math.min(1, ch[v] / top) * (H - 4));
    ctx.lineTo(W, H);
    ctx.closePath();
    ctx.fill();
  });
  ctx.globalCompositeOperation = "source-over";
}

// Highlights clipped in red, shadows crushed in blue, over the corrected image.
function drawClipping() {
  const overlay = $("clip-overlay"), img = $("img-corrected");
  if (!img.naturalWidth) return;
  const src = imagePixels(img, 9e6);
  overlay.width = src.width; overlay.height = src.height;
  const ctx = overlay.getContext("2d");
  const out = ctx.createImageData(src.width, src.height);
  const a = src.data, o = out.data;
  let marked = 0;
  for (let i = 0; i < a.length; i += 4) {
    if (a[i] >= CLIP_HIGH || a[i + 1] >= CLIP_HIGH || a[i + 2] >= CLIP_HIGH) {
      o[i] = 255; o[i + 1] = 0; o[i + 2] = 0; o[i + 3] = 255; marked++;
    } else if (a[i] <= CLIP_LOW && a[i + 1] <= CLIP_LOW && a[i + 2] <= CLIP_LOW) {
      o[i] = 40; o[i + 1] = 90; o[i + 2] = 255; o[i + 3] = 255; marked++;
    }
  }
  ctx.putImageData(out, 0, 0);
  overlay.dataset.marked = String(marked);
  overlay.hidden = false;
}

// ---- several lights

// Lights of the map that differ by more than 3 degrees (the confidence's own
// "error under 3 degrees") are counted as different lights.
const LIGHTS_APART_DEG = 3;

function angleDeg(a, b) {
  const dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const n = Math.hypot(...a) * Math.hypot(...b);
  return Math.acos(Math.min(1, Math.max(-1, dot / n))) * 180 / Math.PI;
}

// The angle (degrees) from g to the nearest non-negative mixture of a and b (Infinity if none is near).
function mixtureAngle(g, a, b) {
  const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  const aa = dot(a, a), ab = dot(a, b), bb = dot(b, b), ga = dot(g, a), gb = dot(g, b);
  const det = aa * bb - ab * ab;
  if (Math.abs(det) < 1e-12) return Infinity;
  const al = (ga * bb - gb * ab) / det, be = (gb * aa - ga * ab) / det;
  if (al < 0 || be < 0) return Infinity;
  return angleDeg(g, [al * a[0] + be * b[0], al * a[1] + be * b[1], al * a[2] + be * b[2]]);
}

function showLights(analysis) {
  // one light (the usual case) is said under Technical details only
  const lm = analysis.light_map, d = analysis.diagnostics || {};
  const box = $("lights"), canvas = $("light-map");
  box.hidden = !lm;
  canvas.hidden = !lm;
  $("lights-reason").textContent = pageWords(String(d.spatial_reason || ""));
  if (!lm) return;
  const rows = lm.camera_rgb, cells = rows.flat();
  const groups = [];
  for (const c of cells) if (!groups.some((g) => angleDeg(g, c) <= LIGHTS_APART_DEG)) groups.push(c);
  // light is additive: a region lit by a mixture of two others' lights is not a light of its own
  const pure = groups.filter((g) => !groups.some((a) => a !== g && groups.some((b) => b !== g && b !== a &&
    mixtureAngle(g, a, b) <= LIGHTS_APART_DEG)));
  const n = Math.max(1, pure.length);
  let spread = 0;
  for (const a of cells) for (const b of cells) spread = Math.max(spread, angleDeg(a, b));
  $("lights-title").textContent = n > 1
    ? `${n} lights found${groups.length > n ? ", mixing in between" : ""} (they differ by up to ${fmt(spread, 1)}°)`
    : `One light, varying by ${fmt(spread, 1)}° over the picture`;
  canvas.dataset.lights = String(n);
  // each region coloured by its light relative to the light the picture is corrected for:
  // a region whose light is bluer than that shows blue (what is left on a white surface there)
  const ref = (analysis.illuminant || {}).camera_rgb || cells[0];
  const W = canvas.width, H = Math.max(20, Math.round(W * (view.H || 2) / (view.W || 3)));
  canvas.height = H;
  const ctx = canvas.getContext("2d");
  const rf = lm.centres_row_fraction, cf = lm.centres_col_fraction;
  const nearest = (arr, f) => arr.reduce((best, v, i) => Math.abs(v - f) < Math.abs(arr[best] - f) ? i : best, 0);
  const img = ctx.createImageData(W, H);
  for (let y = 0; y < H; y++) {
    const i = nearest(rf, (y + 0.5) / H);
    for (let x = 0; x < W; x++) {
      const c = rows[i][nearest(cf, (x + 0.5) / W)];
      const rel = [c[0] / ref[0], c[1] / ref[1], c[2] / ref[2]];
      const m = Math.max(...rel);
      const k = 4 * (y * W + x);
      for (let ch = 0; ch < 3; ch++) img.data[k + ch] = Math.round(255 * Math.pow(0.85 * rel[ch] / m, 1 / 2.2));
      img.data[k + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
}

async function downloadCorrected(format, ext, white) {
  if (!current || !current.options) return;
  const w = white || whiteField();
  const fields = Object.assign(renderFields(w), {format});
  $("dl-status").textContent = `Rendering the full-resolution ${format.toUpperCase()}…`;
  $("error").hidden = true;
  try {
    const resp = await post("/v1/white-balance", formFor(current.file, fields));
    const name = format === "xmp" ? `${stem(current.file.name)}.xmp`
      : format === "dng" ? `${stem(current.file.name)}.wandell.dng`
      : `${stem(current.file.name)}-${w === "as-shot" ? "as-shot" : "corrected"}.${ext}`;
    saveBlob(await resp.blob(), name);
    $("dl-status").textContent = "";
  } catch (err) {
    $("dl-status").textContent = "";
    showError($("error"), err);
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
  const running = c.running || 0;   // pending counts only the items not started (probe round 9c)
  const total = c.total || done + failed + pending + running + cancelled;
  const settled = batchSettled(j);
  const bar = $("batch-progress");
  bar.max = Math.max(1, total);
  // the bar shows the work done: a cancelled item was not done (a batch
  // cancelled before anything ran shows an empty bar, not a full one)
  bar.value = done + failed;
  bar.classList.toggle("cancelled", j.status === "cancelled");
  const state = j.status === "cancelled" && !settled
    ? `cancelling (${running} running item${running === 1 ? "" : "s"} stopping)`
    : j.status === "done" ? "finished" : j.status;
  let s = `Batch ${j.id}: ${state}. ${done} done, ${failed} failed, ${pending} pending` +
    (running && j.status !== "cancelled" ? `, ${running} running` : "") +
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
  $("batch-remove").hidden = !settled;
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
    const resp = await fetch(`/v1/batches/${encodeURIComponent(mine.id)}`).catch((e) => {
      throw new Error(`Could not reach the service (${e.message}).`);
    });
    if (!resp.ok) throw await failure(resp);
    const j = await resp.json();
    if (batch !== mine) return;   // another batch was started meanwhile
    if (mine.retries) { mine.retries = 0; $("batch-error").hidden = true; }   // back in touch
    const settled = renderBatch(j);
    if (!settled) mine.timer = setTimeout(poll, 500);
    else { $("batch-run").disabled = batchFiles.length === 0; }
  } catch (err) {
    if (batch !== mine) return;
    showError($("batch-error"), err);
    // the server restarting (its batches resume when it is back), its job store busy (503 with
    // Retry-After), too many connections, or a proxy in front of it meanwhile: the batch goes on, so
    // the page keeps following it (probe round 9: one failed poll stopped the page for good);
    // anything else (404: the batch was removed) is final
    if (!(err instanceof ApiError) || [429, 502, 503, 504].includes(err.status)) {
      mine.retries = (mine.retries || 0) + 1;
      const wait = err.retryAfter || Math.min(30, 2 ** mine.retries);
      $("batch-error").textContent += ` Trying again in ${wait} s.`;
      mine.timer = setTimeout(poll, 1000 * wait);
      return;
    }
    $("batch-run").disabled = batchFiles.length === 0;
  }
}

async function startBatch() {
  if (!batchFiles.length) return;
  if (batch && batch.timer) clearTimeout(batch.timer);
  $("batch-error").hidden = true;
  $("batch-note").hidden = true;
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

// Removes a settled batch and its files from the server (DELETE ?remove=true:
// a plain DELETE only cancels), after the user confirms.
async function removeBatch() {
  if (!batch) return;
  const mine = batch;
  if (!window.confirm("Delete this batch and its results from the server? Downloaded files stay.")) return;
  $("batch-remove").disabled = true;
  try {
    const resp = await fetch(`/v1/batches/${encodeURIComponent(mine.id)}?remove=true`, {method: "DELETE"});
    if (!resp.ok) throw await failure(resp);
    const j = await resp.json();
    if (batch !== mine) return;
    batch = null;
    $("batch-view").hidden = true;
    $("batch-remove").hidden = true;
    $("batch-status").textContent = "";
    $("batch-error").hidden = true;
    const note = $("batch-note");
    note.hidden = false;
    note.textContent = `Batch removed from the server (${fmt(j.freed_bytes / 1e6, 1)} MB freed).`;
  } catch (err) {
    showError($("batch-error"), err);
  } finally {
    $("batch-remove").disabled = false;
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
  wireViewer();
  $("neutral-clear").addEventListener("click", () => {
    if (current) { current.neutral = null; current.picks = []; current.wb = {mode: "auto"}; run(); }
  });
  $("view-split").addEventListener("click", () => setMode("split"));
  $("view-before").addEventListener("click", () => setMode("before"));
  $("view-after").addEventListener("click", () => setMode("after"));
  $("zoom-fit").addEventListener("click", () => setZoom("fit"));
  $("zoom-100").addEventListener("click", () => setZoom("100"));
  $("show-clipping").addEventListener("change", () => {
    if ($("show-clipping").checked) drawClipping(); else $("clip-overlay").hidden = true;
  });
  $("wb-asshot").addEventListener("click", () => setWhiteMode("as-shot"));
  $("wb-auto").addEventListener("click", () => setWhiteMode("auto"));
  $("wb-custom").addEventListener("click", () => setWhiteMode("custom"));
  $("temp").addEventListener("input", onSlider);
  $("tint").addEventListener("input", onSlider);
  const customTarget = () => {
    const v = $("opt-target").value;
    $("target-k-label").hidden = !(v === "custom-D" || v === "custom-BB");
    if (v === "custom-D" && Number($("target-k").value) < 4000) $("target-k").value = 5600;
    if (v === "custom-BB" && !$("target-k").value) $("target-k").value = 3200;
  };
  $("opt-target").addEventListener("change", () => { customTarget(); if (current && current.estimate) run(); });
  $("target-k").addEventListener("change", () => { if (current && current.estimate) run(); });
  $("dl-tiff").addEventListener("click", () => downloadCorrected("tiff", "tif"));
  $("dl-png").addEventListener("click", () => downloadCorrected("png", "png"));
  $("dl-jpeg").addEventListener("click", () => downloadCorrected("jpeg", "jpg"));
  $("dl-json").addEventListener("click", downloadEstimate);
  $("dl-asshot").addEventListener("click", () => downloadCorrected("png", "png", "as-shot"));
  $("dl-xmp").addEventListener("click", () => downloadCorrected("xmp", "xmp"));
  $("dl-dng").addEventListener("click", () => downloadCorrected("dng", "dng"));
  $("batch-files").addEventListener("change", (e) => chooseBatch(e.target.files));
  dropZone($("batch-drop"), $("batch-files"), chooseBatch);
  $("batch-run").addEventListener("click", startBatch);
  $("batch-cancel").addEventListener("click", cancelBatch);
  $("batch-remove").addEventListener("click", removeBatch);
});
