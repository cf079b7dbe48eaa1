// Zones (archive view --zones FIELDS): the fields as outlines over the map (/api/zones, lon/lat), and a
// click inside one plots its time series, one point per flight (/api/zones/series: the zone's
// statistics as archive stats computes them, by the server's own code), of the index the display shows:
// NDVI, or the index display's (a - b) / (a + b) when its bands are not NDVI's; in reflectance (archive
// stats' default), else (flights without downwelling spectra) in the display's mode.
// The chart (uPlot, as the spectrum's): x the flight's date, y the mean with the p10..p90 spread, the
// legend the values under the cursor. The served stack's flights when a stack is shown.
import { nearestBand } from "./params.js";
import uPlot from "./vendor/uplot/uPlot.esm.js";
import { geometryBox, inGeometry, map } from "./map.js";
import { $, fmt, getJSON, referenceFlight, viewer } from "./state.js";

const state = { features: [], layer: null, selected: null, chart: null, asked: 0 };
map.createPane("zones").style.zIndex = 410;   // over the imagery and the stack, outlines only (no pointer events)

function style(f) {
  const on = f.id === state.selected;
  return { color: on ? "#00e5ff" : "#0097a7", weight: on ? 3 : 1.5, fill: false, dashArray: on ? null : "4 3" };
}

function drawZones() {
  if (state.layer) state.layer.remove();
  state.layer = L.geoJSON({ type: "FeatureCollection", features: state.features },
                          { pane: "zones", interactive: false, style });
  if ($("show-zones").checked) state.layer.addTo(map);
}

// the zone under a point (degrees): the smallest box of those holding it
function zoneAt(lng, lat) {
  const area = (f) => { const [w, s, e, n] = geometryBox(f.geometry); return (e - w) * (n - s); };
  const under = state.features.filter((f) => f.geometry && inGeometry(lng, lat, f.geometry));
  return under.sort((a, b) => area(a) - area(b))[0] || null;
}

// what the display shows: NDVI, or the index display's two bands when they are not NDVI's
function indexParams() {
  const q = new URLSearchParams();
  if ($("display").value === "index") {
    const a = Number($("index-a").value), b = Number($("index-b").value);
    const ref = viewer.byId.get(referenceFlight());
    const wl = ref && ref.properties.wavelength;
    const ndvi = wl ? [wl[nearestBand(ref, 830)], wl[nearestBand(ref, 654)]] : null;
    if (!(ndvi && ndvi[0] === a && ndvi[1] === b) && Number.isFinite(a) && Number.isFinite(b)) {
      q.set("a", String(a)); q.set("b", String(b));
    }
  }
  if (!q.has("a")) q.set("index", "NDVI");
  const stack = viewer.stacks && viewer.stacks.state.open;
  if (stack) q.set("stack", stack.name);
  return q;
}

async function askSeries(feature) {
  state.selected = feature.id;
  drawZones();
  $("zone-section").hidden = false;
  const q = indexParams();
  q.set("zone", feature.id);
  const asked = ++state.asked;
  viewer.zoneAsked = performance.now();
  $("zone-title").textContent = `zone ${feature.id}: ${q.get("index") || `(a − b) / (a + b), a ${q.get("a")} nm, b ${q.get("b")} nm`}`;
  $("zone-message").textContent = "computing…";
  $("zone-message").classList.remove("error");
  let answer, note = "";
  try { answer = await getJSON(`/api/zones/series?${q}`); }
  catch (e) {
    // in reflectance (archive stats' default) unless the flights cannot give it: then the display's mode
    if (asked === state.asked && $("mode").value) {
      q.set("mode", $("mode").value);
      note = `(${e.message}) `;
      try { answer = await getJSON(`/api/zones/series?${q}`); } catch (again) { note = again.message; }
    } else note = e.message;
  }
  if (asked !== state.asked) return;   // a later click's answer is the one shown
  if (!answer) {
    $("zone-message").textContent = note;
    $("zone-message").classList.add("error");
    return;
  }
  viewer.zoneSeries = answer;
  plot(answer);
  if (note) $("zone-message").textContent = note + $("zone-message").textContent;
  viewer.zonePlotted = performance.now();
}

const dateText = (t) => new Date(t * 1000).toISOString().slice(0, 16).replace("T", " ");

function plot(answer) {
  const box = $("zone-series");
  if (state.chart) { state.chart.destroy(); state.chart = null; }
  viewer.zoneChart = null;
  box.replaceChildren();
  const imaged = answer.rows.filter((r) => r.count);
  $("zone-title").textContent = `zone ${answer.zone}: ${answer.index} (${answer.mode}${answer.bands ? `; ${answer.bands}` : ""})`;
  $("zone-message").textContent = answer.message ||
    `${imaged.length} of ${answer.rows.length} flight${answer.rows.length === 1 ? "" : "s"} image it; ` +
    `${answer.gsd} m grid, ${answer.seconds} s`;
  if (!imaged.length) return;
  const rows = answer.rows;
  const data = [rows.map((r) => Date.parse(r.datetime) / 1000), rows.map((r) => r.p10), rows.map((r) => r.mean),
                rows.map((r) => r.p90)];
  const width = Math.max(200, Math.floor($("zone-section").clientWidth || 330));   // the box is empty: its section's
  const value = (u, v) => fmt(v, 5);
  const font = `10px system-ui, -apple-system, "Segoe UI", Roboto, Arial, sans-serif`;
  const axis = { font, labelFont: font, stroke: "#334", ticks: { stroke: "#445", size: 4 } };
  const opts = {
    width, height: Math.round(width * 0.6), title: `zone ${answer.zone}: ${answer.index}`,
    // the first and last flights' points inside the plot (a day's margin for one flight)
    scales: { x: { time: true, range: (u, lo, hi) => { const pad = Math.max((hi - lo) * 0.08, lo === hi ? 86400 : 0);
                                                      return [lo - pad, hi + pad]; } } },
    axes: [{ ...axis, space: 60 }, { ...axis, label: `${answer.index} (${answer.mode})`, labelSize: 14, size: 46,
                                     grid: { stroke: "#e3e6eb" } }],
    series: [
      { label: "UTC", value: (u, t) => (t === null ? "–" : dateText(t)) },
      { label: "p10", stroke: "#7fb3d5", width: 1, dash: [3, 3], value },
      { label: "mean", stroke: "#1f77b4", width: 2, value, points: { show: true, size: 7 } },
      { label: "p90", stroke: "#7fb3d5", width: 1, dash: [3, 3], value },
    ],
    bands: [{ series: [3, 1], fill: "rgba(31, 119, 180, 0.15)" }],
    legend: { live: true },
  };
  state.chart = new uPlot(opts, data, box);
  viewer.zoneChart = state.chart;
  requestAnimationFrame(() => box.scrollIntoView({ block: "nearest" }));
}

function showZones(found) {
  state.features = found.features || [];
  state.selected = null;
  viewer.zones = state.features;
  $("zone-section").hidden = !state.features.length && !document.body.classList.contains("zones-served");
  $("zone-message").classList.remove("error");
  $("zone-message").textContent = `${state.features.length} zone${state.features.length === 1 ? "" : "s"} from ${found.path}: click one`;
  drawZones();
}

// the zones served (called once at the page's start); the section shows once the server answers
export async function loadZones() {
  let found;
  try { found = await getJSON("/api/zones"); } catch (e) { return; }
  document.body.classList.add("zones-served");
  $("zone-section").hidden = false;
  if (found.features.length) showZones(found);
  else $("zone-message").textContent = "no zones: load a GeoJSON file, or serve one with archive view --zones";
}

// a GeoJSON file loaded in the page (the file input, or dropped on the map): the server reads it as
// --zones reads a file (the same refusals, shown here) and serves it instead
async function sendZones(file) {
  $("zone-message").classList.remove("error");
  $("zone-message").textContent = `reading ${file.name}…`;
  try {
    const found = await getJSON(`/api/zones?name=${encodeURIComponent(file.name)}`,
                                { method: "POST", body: await file.text(), headers: { "Content-Type": "application/geo+json" } });
    showZones(found);
    if (state.layer && state.features.length) map.fitBounds(state.layer.getBounds(), { maxZoom: 21 });
  } catch (e) {
    $("zone-message").textContent = e.message;
    $("zone-message").classList.add("error");
  }
}
$("zone-file").addEventListener("change", () => { const f = $("zone-file").files[0]; if (f) sendZones(f); });
const mapBox = map.getContainer();
mapBox.addEventListener("dragover", (e) => { if (document.body.classList.contains("zones-served")) e.preventDefault(); });
mapBox.addEventListener("drop", (e) => {
  const f = e.dataTransfer && e.dataTransfer.files[0];
  if (!f || !document.body.classList.contains("zones-served")) return;
  e.preventDefault();
  sendZones(f);
});

$("show-zones").addEventListener("change", drawZones);
map.on("click", (e) => {
  const zone = zoneAt(e.latlng.lng, e.latlng.lat);
  if (zone) askSeries(zone);
});
viewer.zoneState = state;
