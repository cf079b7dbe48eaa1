// archive view: the catalog map, a flight drawn as tiles by the server's inverse renderer, and the
// spectrum of a clicked pixel. State lives in window.viewer (the browser test reads it).
"use strict";

const $ = (id) => document.getElementById(id);
const viewer = (window.viewer = {
  map: null, footprints: null, layer: null, flight: null, info: null,
  ready: false, loads: 0, tileErrors: 0, lastPoint: null, stretchRanges: null, marker: null,
});

const map = L.map("map", { maxZoom: 24, fadeAnimation: false, attributionControl: false, worldCopyJump: false });
map.setView([20, 0], 2);
L.control.scale({ imperial: false }).addTo(map);
viewer.map = map;

function status(text, isError = false) {
  const el = $("status");
  el.textContent = text || "";
  el.classList.toggle("error", !!isError);
}

async function getJSON(url) {
  const response = await fetch(url);
  let body = null;
  try { body = await response.json(); } catch (e) { /* not JSON */ }
  if (!response.ok) throw new Error((body && body.error) || `${response.status} ${response.statusText}`);
  return body;
}

const fmt = (v, digits = 4) => (v === null || v === undefined ? "–" : Number(v).toPrecision(digits));
const idPath = () => `/api/collections/${encodeURIComponent(viewer.flight.id)}`;

function clampedBounds() {
  const b = map.getBounds();
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));
  return [clamp(b.getWest(), -180, 180), clamp(b.getSouth(), -85, 85),
          clamp(b.getEast(), -180, 180), clamp(b.getNorth(), -85, 85)].map((v) => v.toFixed(7)).join(",");
}

// ---- catalog ------------------------------------------------------------------------------
async function loadCatalog(fit) {
  const q = new URLSearchParams();
  if ($("f-inview").checked) q.set("bbox", clampedBounds());
  if ($("f-datetime").value.trim()) q.set("datetime", $("f-datetime").value.trim());
  if ($("f-wavelength").value.trim()) q.set("wavelength", $("f-wavelength").value.trim());
  let fc;
  try { fc = await getJSON(`/api/collections?${q}`); } catch (e) { status(e.message, true); return; }
  if (viewer.footprints) viewer.footprints.remove();
  viewer.footprints = L.geoJSON(fc, {
    style: { color: "#ffcc33", weight: 2, fill: true, fillOpacity: 0.0, interactive: true },
    onEachFeature: (feature, layer) => {
      layer.bindTooltip(feature.id, { sticky: true });
      layer.on("click", (ev) => { if (!viewer.flight) { L.DomEvent.stop(ev); openFlight(feature); } });
    },
  });
  if ($("show-footprints").checked) viewer.footprints.addTo(map);
  const list = $("flights");
  list.replaceChildren();
  for (const f of fc.features) {
    const p = f.properties;
    const li = document.createElement("li");
    li.dataset.id = f.id;
    li.textContent = f.id;
    const meta = document.createElement("span");
    meta.className = "meta";
    meta.textContent = `${p.start_datetime.slice(0, 19).replace("T", " ")} · ${p.bands} bands ` +
      `${fmt(p.min_wavelength, 4)}–${fmt(p.max_wavelength, 4)} nm · ${p.cubes ?? "?"} cubes · ${fmt(p.gsd, 2)} m`;
    li.append(meta);
    li.addEventListener("click", () => openFlight(f));
    list.append(li);
  }
  status(`${fc.features.length} flight(s)`);
  if (fit && fc.features.length) map.fitBounds(viewer.footprints.getBounds(), { padding: [20, 20] });
}

$("filters").addEventListener("submit", (ev) => { ev.preventDefault(); loadCatalog(false); });
$("show-footprints").addEventListener("change", () => {
  if (!viewer.footprints) return;
  if ($("show-footprints").checked) viewer.footprints.addTo(map); else viewer.footprints.remove();
});

// ---- a flight -----------------------------------------------------------------------------
function fillBands(select, wavelengths, count) {
  select.replaceChildren();
  for (let i = 0; i < count; i++) {
    const o = document.createElement("option");
    o.value = String(i);
    o.textContent = wavelengths ? `${i}: ${wavelengths[i].toFixed(1)} nm` : `band ${i}`;
    select.append(o);
  }
}

function setDefaults() {
  const info = viewer.info;
  const [r, g, b] = info.default_bands;
  $("band-r").value = r; $("band-g").value = g; $("band-b").value = b; $("band-grey").value = r;
  $("display").value = "rgb";
  $("mode").value = info.default_mode;
  $("stretch").value = "flight";
  viewer.stretchRanges = null;
  $("cube-first").value = 0; $("cube-last").value = info.cubes.length - 1;
  const gh = info.ground_height;
  const ground = $("ground");
  // over a DEM (a collection ingested with --dem) the slider is the DEM's vertical offset
  document.querySelector('label[for="ground"]').textContent = info.terrain ? "DEM offset" : "Ground";
  ground.title = info.terrain ? `vertical offset of ${info.terrain.dem}, metres` : "flat ground height, metres";
  ground.min = (gh - (info.terrain ? 10 : 30)).toFixed(1);
  ground.max = (info.terrain ? gh + 10 : Math.min(gh + 30, info.lowest_camera - 1.5)).toFixed(1);
  ground.value = gh;
  const sync = $("sync");
  sync.min = (info.sync_offset - 0.25).toFixed(3); sync.max = (info.sync_offset + 0.25).toFixed(3);
  sync.value = info.sync_offset;
  showDisplay();
  showOutputs();
}

async function openFlight(feature) {
  status(`opening ${feature.id}…`);
  let info;
  try { info = await getJSON(`/api/collections/${encodeURIComponent(feature.id)}`); }
  catch (e) { status(e.message, true); return; }
  closeFlight();
  viewer.flight = feature;
  viewer.info = info;
  for (const li of $("flights").children) li.classList.toggle("open", li.dataset.id === feature.id);
  $("flight-title").textContent = feature.id;
  for (const id of ["band-r", "band-g", "band-b", "band-grey"]) fillBands($(id), info.wavelength, info.bands);
  const mode = $("mode");
  mode.replaceChildren(...info.modes.map((m) => { const o = document.createElement("option"); o.value = m; o.textContent = m; return o; }));
  $("cube-first").max = $("cube-last").max = info.cubes.length - 1;
  setDefaults();
  $("controls").hidden = false;
  const bounds = L.geoJSON(feature).getBounds();
  map.fitBounds(bounds, { padding: [30, 30] });
  updateLayer();
  status(`${feature.id}: ${info.cubes.length} cubes, ${info.bands} bands`);
}

function closeFlight() {
  if (viewer.layer) viewer.layer.remove();
  if (viewer.marker) viewer.marker.remove();
  viewer.layer = viewer.flight = viewer.info = viewer.marker = viewer.lastPoint = null;
  viewer.ready = false;
  $("controls").hidden = true;
  $("pixel").hidden = true;
  for (const li of $("flights").children) li.classList.remove("open");
}

function commonParams() {
  const q = new URLSearchParams();
  const info = viewer.info;
  q.set("mode", $("mode").value);
  const first = Number($("cube-first").value), last = Number($("cube-last").value);
  if (first !== 0 || last !== info.cubes.length - 1) q.set("cubes", `${first}-${last}`);
  const gh = Number($("ground").value);
  if (gh !== info.ground_height) q.set("ground_height", String(gh));
  const sync = Number($("sync").value);
  if (sync !== info.sync_offset) q.set("sync_offset", String(sync));
  return q;
}

function channelParams(q) {
  const info = viewer.info;
  if ($("display").value === "grey") {
    q.set("band", $("band-grey").value);
  } else {
    const bands = ["band-r", "band-g", "band-b"].map((id) => Number($(id).value));
    q.set("wavelengths", bands.map((b) => (info.wavelength ? info.wavelength[b] : b)).join(","));
  }
  return q;
}

function tileQuery() {
  const q = channelParams(commonParams());
  if ($("stretch").value === "view" && viewer.stretchRanges) q.set("stretch", viewer.stretchRanges.flat().map((v) => v.toPrecision(7)).join(","));
  else q.set("stretch", "p2,p98");
  return q;
}

function paddedBounds() {
  const b = L.geoJSON(viewer.flight).getBounds();
  return b.pad(1.0);  // the footprint grows when the ground is lowered: leave room
}

function updateLayer() {
  if (!viewer.flight) return;
  const url = `${idPath()}/tiles/{z}/{x}/{y}.png?${tileQuery()}`;
  viewer.ready = false;
  viewer.tileUrl = url;
  if (viewer.layer) { viewer.layer.setUrl(url); return; }
  viewer.layer = L.tileLayer(url, {
    maxZoom: 24, maxNativeZoom: 24, tileSize: 256, keepBuffer: 1, className: "flight-tiles",
    bounds: paddedBounds(), updateWhenZooming: false,
  });
  viewer.layer.on("loading", () => { viewer.ready = false; });
  viewer.layer.on("load", () => { viewer.ready = true; viewer.loads += 1; });
  viewer.layer.on("tileerror", () => { viewer.tileErrors += 1; status("a tile failed to load", true); });
  viewer.layer.addTo(map);
}

function showDisplay() {
  const grey = $("display").value === "grey";
  for (const el of document.querySelectorAll(".row.rgb")) el.hidden = grey;
  for (const el of document.querySelectorAll(".row.grey")) el.hidden = !grey;
}

function showOutputs() {
  $("ground-out").textContent = `${Number($("ground").value).toFixed(1)} m`;
  $("sync-out").textContent = `${Number($("sync").value).toFixed(3)} s`;
  const r = viewer.stretchRanges;
  $("stretch-values").textContent = $("stretch").value === "view" && r
    ? r.map(([lo, hi]) => `${fmt(lo)}…${fmt(hi)}`).join("  ") : "2 %/98 % of the whole flight";
}

let debounce = null;
function changed(delay = 0) {
  showOutputs();
  clearTimeout(debounce);
  debounce = setTimeout(updateLayer, delay);
}

for (const id of ["band-r", "band-g", "band-b", "band-grey", "mode", "cube-first", "cube-last"]) {
  $(id).addEventListener("change", () => {
    if (id === "mode" || id.startsWith("band")) { viewer.stretchRanges = null; $("stretch").value = "flight"; }
    changed();
  });
}
$("display").addEventListener("change", () => { viewer.stretchRanges = null; $("stretch").value = "flight"; showDisplay(); changed(); });
$("stretch").addEventListener("change", () => { if ($("stretch").value === "view") stretchFromView(); else changed(); });
for (const id of ["ground", "sync"]) {
  $(id).addEventListener("input", () => changed(150));
  $(id).addEventListener("change", () => changed());
}
$("truecolour").addEventListener("click", () => {
  const [r, g, b] = viewer.info.default_bands;
  $("band-r").value = r; $("band-g").value = g; $("band-b").value = b;
  $("display").value = "rgb"; viewer.stretchRanges = null; $("stretch").value = "flight";
  showDisplay(); changed();
});
$("stretch-view").addEventListener("click", () => stretchFromView());
$("per-channel").addEventListener("change", () => { if ($("stretch").value === "view") stretchFromView(); });
$("reset").addEventListener("click", () => { setDefaults(); changed(); });
$("close").addEventListener("click", () => { closeFlight(); status(""); });

async function stretchFromView() {
  if (!viewer.flight) return;
  const q = channelParams(commonParams());
  q.set("bbox", clampedBounds());
  let st;
  try { st = await getJSON(`${idPath()}/stats?${q}`); } catch (e) { status(e.message, true); return; }
  if (!st.count) { status("no pixel of the flight in view", true); return; }
  let ranges = st.low.map((lo, i) => [lo, st.high[i] > lo ? st.high[i] : lo + 1]);
  if (!$("per-channel").checked) {
    const lo = Math.min(...ranges.map((r) => r[0])), hi = Math.max(...ranges.map((r) => r[1]));
    ranges = ranges.map(() => [lo, hi]);
  }
  viewer.stretchRanges = ranges;
  $("stretch").value = "view";
  changed();
}

// ---- a pixel ------------------------------------------------------------------------------
map.on("click", async (ev) => {
  if (!viewer.flight) return;
  const q = commonParams();
  q.set("lon", ev.latlng.lng.toFixed(9));
  q.set("lat", ev.latlng.lat.toFixed(9));
  if (viewer.flight.properties.gsd) q.set("gsd", String(viewer.flight.properties.gsd));
  let p;
  try { p = await getJSON(`${idPath()}/point?${q}`); } catch (e) { status(e.message, true); return; }
  viewer.lastPoint = p;
  if (viewer.marker) viewer.marker.remove();
  viewer.marker = L.circleMarker([p.pixel.lat, p.pixel.lon], { radius: 5, color: "#ff3366", weight: 2, fill: false }).addTo(map);
  showPixel(p);
});

function showPixel(p) {
  $("pixel").hidden = false;
  const rows = p.covered ? [
    ["cube", `${p.cube} (${p.base})`], ["line, sample", `${p.line}, ${p.sample}`],
    ["time", `${p.utc} (${p.time.toFixed(4)} s)`],
  ] : [["pixel", "no line of the flight covers it"]];
  rows.push(["centre", `${p.pixel.lat.toFixed(7)}, ${p.pixel.lon.toFixed(7)}`],
            ["EPSG:" + p.epsg, `${p.pixel.x.toFixed(3)} E, ${p.pixel.y.toFixed(3)} N (${p.gsd} m)`],
            ["mode", p.mode + (p.saturated ? " (saturated)" : "")],
            ["ground, sync", `${p.ground_height.toFixed(2)} m, ${p.sync_offset.toFixed(3)} s`]);
  $("pixel-info").replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const th = document.createElement("th"); th.textContent = k;
    const td = document.createElement("td"); td.textContent = v;
    tr.append(th, td);
    return tr;
  }));
  drawSpectrum(p);
  const xs = p.wavelength || p.values.map((_, i) => i);
  const csv = [`${p.wavelength ? "wavelength_nm" : "band"},${p.mode}`]
    .concat(p.values.map((v, i) => `${xs[i]},${v === null ? "" : v}`)).join("\n") + "\n";
  const link = $("csv");
  if (link.href.startsWith("blob:")) URL.revokeObjectURL(link.href);
  link.href = URL.createObjectURL(new Blob([csv], { type: "text/csv" }));
  link.download = `${p.id}_cube${p.cube}_line${p.line}_sample${p.sample}.csv`;
  viewer.csv = csv;
}

function niceTicks(lo, hi, n = 5) {
  if (!(hi > lo)) { hi = lo + 1; }
  const step0 = (hi - lo) / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0);
  const ticks = [];
  for (let t = Math.ceil(lo / step) * step; t <= hi + step * 1e-9; t += step) ticks.push(Number(t.toPrecision(12)));
  return ticks;
}

function drawSpectrum(p) {
  const svg = $("spectrum");
  const NS = "http://www.w3.org/2000/svg";
  const W = 340, H = 190, left = 52, right = 10, top = 10, bottom = 32;
  const xs = p.wavelength || p.values.map((_, i) => i);
  const finite = p.values.filter((v) => v !== null);
  svg.replaceChildren();
  const el = (name, attrs, text) => {
    const e = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    svg.append(e);
    return e;
  };
  const x0 = Math.min(...xs), x1 = Math.max(...xs);
  let y0 = finite.length ? Math.min(...finite) : 0, y1 = finite.length ? Math.max(...finite) : 1;
  if (y1 === y0) { y0 -= 1; y1 += 1; }
  const pad = (y1 - y0) * 0.05; y0 -= pad; y1 += pad;
  const sx = (x) => left + ((x - x0) / (x1 - x0 || 1)) * (W - left - right);
  const sy = (y) => top + (1 - (y - y0) / (y1 - y0)) * (H - top - bottom);
  for (const t of niceTicks(y0, y1)) {
    el("line", { class: "grid", x1: left, x2: W - right, y1: sy(t), y2: sy(t) });
    el("text", { x: left - 4, y: sy(t) + 3, "text-anchor": "end" }, Math.abs(t) >= 1e4 ? t.toExponential(1) : String(t));
  }
  for (const t of niceTicks(x0, x1)) {
    el("line", { class: "axis", x1: sx(t), x2: sx(t), y1: H - bottom, y2: H - bottom + 4 });
    el("text", { x: sx(t), y: H - bottom + 14, "text-anchor": "middle" }, String(t));
  }
  el("path", { class: "axis", d: `M${left},${top}V${H - bottom}H${W - right}` });
  el("text", { x: (left + W - right) / 2, y: H - 4, "text-anchor": "middle" }, p.wavelength ? "wavelength (nm)" : "band");
  el("text", { x: 10, y: (top + H - bottom) / 2, "text-anchor": "middle", transform: `rotate(-90 10 ${(top + H - bottom) / 2})` }, p.mode);
  // one polyline per run of values (a NaN band breaks the line)
  let run = [];
  const flush = () => { if (run.length) el("polyline", { class: "line", points: run.join(" ") }); run = []; };
  p.values.forEach((v, i) => { if (v === null) flush(); else run.push(`${sx(xs[i]).toFixed(2)},${sy(v).toFixed(2)}`); });
  flush();
}

loadCatalog(true);
