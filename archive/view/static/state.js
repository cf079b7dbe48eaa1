// archive view: the page's one state object. Every module imports it from here (no page script
// declares a global); it is also window.viewer, the one name the page adds for the browser tests and
// the bench, which read it (with Leaflet's L). And the small helpers every module uses: elements,
// numbers, JSON requests (carrying the view generation), the status line and the errors shown next
// to the control that caused them.

export const TILE = 256;
export const PALETTE = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2"];
export const MAX_PINS = PALETTE.length;
export const CACHE_BYTES = 384 << 20;  // band planes kept in the browser
export const PREVIEW_UP = 2;           // slider previews: the 256 px tiles 2 zooms up (64 px a shown tile, 1 request per 16)
export const BATCH = 24;               // tiles of flights drawn as ingested asked in one request (/api/values/batch)

export const viewer = {
  // the catalog: features (GeoJSON, as /api/collections), byId, the drawing order (later on top),
  // the hidden ids, each flight's outline as drawn now ({geometry, params}), the overlap rules the
  // server offers ({name, label, key, wins}, the first the default)
  map: null, features: [], byId: new Map(), order: [], hidden: new Set(), outlines: {}, overlaps: [],
  // the open flight (its id, /api/collections/{id}) and every flight's own parameters ({cubes, ground,
  // sync, nav: the navigation source, bs: the boresight [roll, pitch, yaw] degrees})
  open: null, info: null, params: {},
  // spectra: pins, the last clicked point, the CSV of the pins
  pins: [], lastPoint: null, csv: null,
  // the picture: the spec every tile should show (current), the spec id of a refused request
  // (failedSpec), the slider preview shown ({ground|sync|roll|pitch|yaw: value}) and the one waiting (previewNext)
  current: null, failedSpec: null, preview: null, previewNext: null,
  // the stretch: the last ranges drawn, the view's 2-98 % (stretch "view")
  lastRanges: null, viewStretch: null,
  // the view generation: the time (ms) of the latest change of what the page shows; every request
  // carries it (X-Generation) and the server draws the newest generation's requests first
  generation: Date.now(),
  // whether the hash names a map view (no fit to the footprints at boot)
  hashHasMap: false,
  // counters and flags the tests and the bench read
  ready: false, settled: false, draws: 0, loads: 0, requests: 0, tileErrors: 0, pending: 0, specId: null,
  errors: {}, settledAt: 0, previews: 0, booted: false,
};
window.viewer = viewer;

export function newGeneration() { viewer.generation = Math.max(Date.now(), viewer.generation + 1); }
export const generationHeaders = () => ({ "X-Generation": String(viewer.generation) });

export const visibleFlights = () => viewer.order.filter((id) => !viewer.hidden.has(id) && viewer.byId.has(id));
// the flight whose bands and statistics the display controls use: the open one, else the earliest shown
export const referenceFlight = () => viewer.open ||
  (viewer.features.find((f) => !viewer.hidden.has(f.id)) || viewer.features[0] || { id: null }).id;
// the outline of a flight as drawn now (its meshes' edges), else its catalog footprint
export const geometryOf = (id) => (viewer.outlines[id] && viewer.outlines[id].geometry) || viewer.byId.get(id).geometry;

// ---- helpers -----------------------------------------------------------------------------------
export const $ = (id) => document.getElementById(id);
export const fmt = (v, digits = 4) => (v === null || v === undefined || !isFinite(v) ? "–" : Number(v).toPrecision(digits));
export const idPath = (id) => `/api/collections/${encodeURIComponent(id)}`;

export async function getJSON(url, options) {
  const response = await fetch(url, { ...(options || {}), headers: { ...generationHeaders(), ...((options || {}).headers || {}) } });
  let body = null;
  try { body = await response.json(); } catch (e) { /* not JSON */ }
  if (!response.ok) throw new Error((body && body.error) || `${response.status} ${response.statusText}`);
  return body;
}

// a refused answer as an Error (the server's message, its status as .http)
export async function refusal(response) {
  let body = null;
  try { body = await response.json(); } catch (err) { /* not JSON */ }
  return Object.assign(new Error((body && body.error) || `${response.status} ${response.statusText}`), { http: response.status });
}

export function status(text, isError = false) {
  const el = $("status");
  el.textContent = text || "";
  el.classList.toggle("error", !!isError);
}

// errors in words next to the control that caused them (the server names the parameter first)
const ERROR_SLOTS = { cubes: "err-cubes", ground_height: "err-ground", sync_offset: "err-sync", mode: "err-mode",
                      navigation: "err-navigation", boresight: "err-boresight",
                      bands: "err-bands", band: "err-bands", wavelengths: "err-bands", stretch: "err-stretch",
                      bbox: "err-filters", datetime: "err-filters", wavelength: "err-filters" };
export function showError(message, slot) {
  const name = slot || ERROR_SLOTS[(message.match(/^([a-z_]+):/) || [])[1]];
  viewer.errors[name || "status"] = message;
  if (name) { $(name).textContent = message; } else status(message, true);
}
export function clearErrors(...slots) {
  for (const slot of slots.length ? slots : Object.values(ERROR_SLOTS)) { $(slot).textContent = ""; delete viewer.errors[slot]; }
  if (!slots.length) { delete viewer.errors.status; if ($("status").classList.contains("error")) status(""); }
}

// ---- events between modules that must not import each other (tiles.js asks controls.js for a new
// spec: "refresh", or to start the waiting slider preview: "preview") ---------------------------
const listeners = new Map();
export function on(name, fn) { listeners.set(name, [...(listeners.get(name) || []), fn]); }
export function emit(name, ...args) { for (const fn of listeners.get(name) || []) fn(...args); }
