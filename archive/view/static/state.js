// archive view: the page's one state object. Every module imports it from here (no page script
// declares a global); it is also window.viewer, the one name the page adds for the browser tests and
// the bench, which read it (with Leaflet's L).

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
  // the open flight (its id, /api/collections/{id}) and every flight's own parameters ({cubes, ground, sync})
  open: null, info: null, params: {},
  // spectra: pins, the last clicked point, the CSV of the pins
  pins: [], lastPoint: null, csv: null,
  // the picture: the spec every tile should show (current), the spec id of a refused request
  // (failedSpec), the slider preview shown ({ground|sync: value}) and the one waiting (previewNext)
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
