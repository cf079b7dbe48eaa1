// archive view: every flight of the catalog on one map, drawn from band-value tiles (float32 planes
// rendered by the server's inverse renderer) that this page stretches and composes itself, so
// stretch and R/G/B changes among loaded bands need no request; a change that needs new values keeps
// the previous picture until every tile in view has its replacement (double buffering). State
// lives in the URL hash and in window.viewer (the browser tests read it).
"use strict";

const $ = (id) => document.getElementById(id);
const TILE = 256;
const PALETTE = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2"];
const MAX_PINS = PALETTE.length;
const CACHE_BYTES = 384 << 20;      // band planes kept in the browser
const PREVIEW_UP = 2;               // slider previews: the 256 px tiles 2 zooms up (64 px a shown tile, 1 request per 16)
const BATCH = 24;                   // tiles of flights drawn as ingested asked in one request (/api/values/batch)

const viewer = (window.viewer = {
  map: null, features: [], byId: new Map(), order: [], hidden: new Set(), open: null, info: null,
  params: {}, pins: [], lastPoint: null, csv: null, ready: false, settled: false, draws: 0, loads: 0,
  requests: 0, tileErrors: 0, pending: 0, specId: null, errors: {}, settledAt: 0, previews: 0, booted: false,
});

let scheduled = false;      // a pump() is due at the next animation frame

// ---- the map -------------------------------------------------------------------------------
const map = L.map("map", { maxZoom: 24, fadeAnimation: false, attributionControl: false, worldCopyJump: false,
                           scrollWheelZoom: false, zoomSnap: 1, keyboard: true, zoomControl: false });
// the zoom buttons on the right: the top-left corner holds the panel toggle (☰) at every size
L.control.zoom({ position: "topright" }).addTo(map);
map.createPane("footprints").style.zIndex = 150;   // under the imagery (tilePane: 200)
map.setView([20, 0], 2);
L.control.scale({ imperial: false }).addTo(map);
viewer.map = map;

// one zoom level per wheel notch (a notch is ~100 px of deltaY; trackpads add up small deltas)
let wheelSum = 0, wheelTimer = null;
map.getContainer().addEventListener("wheel", (ev) => {
  ev.preventDefault();
  wheelSum += ev.deltaMode === 1 ? ev.deltaY * 33 : ev.deltaY;
  if (Math.abs(wheelSum) < 50 || wheelTimer) return;
  const step = wheelSum > 0 ? -1 : 1;
  wheelSum = 0;
  const z = Math.max(map.getMinZoom(), Math.min(map.getMaxZoom(), map.getZoom() + step));
  map.setZoomAround(map.mouseEventToContainerPoint(ev), z);
  wheelTimer = setTimeout(() => { wheelTimer = null; wheelSum = 0; }, 120);
}, { passive: false });

// ---- small helpers ---------------------------------------------------------------------------
// the view generation: the time (ms) of the latest change of what the page shows; every request
// carries it (X-Generation) and the server draws the newest generation's requests first
let generation = Date.now();
const newGeneration = () => { generation = Math.max(Date.now(), generation + 1); };
const generationHeaders = () => ({ "X-Generation": String(generation) });
async function getJSON(url, options) {
  const response = await fetch(url, { ...(options || {}), headers: { ...generationHeaders(), ...((options || {}).headers || {}) } });
  let body = null;
  try { body = await response.json(); } catch (e) { /* not JSON */ }
  if (!response.ok) throw new Error((body && body.error) || `${response.status} ${response.statusText}`);
  return body;
}
const fmt = (v, digits = 4) => (v === null || v === undefined || !isFinite(v) ? "–" : Number(v).toPrecision(digits));
const idPath = (id) => `/api/collections/${encodeURIComponent(id)}`;

function status(text, isError = false) {
  const el = $("status");
  el.textContent = text || "";
  el.classList.toggle("error", !!isError);
}

// errors in words next to the control that caused them (the server names the parameter first)
const ERROR_SLOTS = { cubes: "err-cubes", ground_height: "err-ground", sync_offset: "err-sync", mode: "err-mode",
                      bands: "err-bands", band: "err-bands", wavelengths: "err-bands", stretch: "err-stretch",
                      bbox: "err-filters", datetime: "err-filters", wavelength: "err-filters" };
function showError(message, slot) {
  const name = slot || ERROR_SLOTS[(message.match(/^([a-z_]+):/) || [])[1]];
  viewer.errors[name || "status"] = message;
  if (name) { $(name).textContent = message; } else status(message, true);
}
function clearErrors(...slots) {
  for (const slot of slots.length ? slots : Object.values(ERROR_SLOTS)) { $(slot).textContent = ""; delete viewer.errors[slot]; }
  if (!slots.length) { delete viewer.errors.status; if ($("status").classList.contains("error")) status(""); }
}

function tileBounds(z, x, y) {
  const n = 2 ** z;
  const lon = (i) => (i / n) * 360 - 180;
  const lat = (j) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * j) / n))) * 180) / Math.PI;
  return [lon(x), lat(y + 1), lon(x + 1), lat(y)];   // W, S, E, N
}
const boxesMeet = (a, b) => a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3];

function pointInRing(x, y, ring) {
  let inside = false;
  for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
    const [xi, yi] = ring[i], [xj, yj] = ring[j];
    if ((yi > y) !== (yj > y) && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) inside = !inside;
  }
  return inside;
}
function inGeometry(lon, lat, g) {
  const polys = g.type === "Polygon" ? [g.coordinates] : g.type === "MultiPolygon" ? g.coordinates : [];
  return polys.some((p) => pointInRing(lon, lat, p[0]) && !p.slice(1).some((h) => pointInRing(lon, lat, h)));
}
function geometryBox(g) {
  const box = [Infinity, Infinity, -Infinity, -Infinity];
  const polys = g.type === "Polygon" ? [g.coordinates] : g.coordinates;
  for (const p of polys) for (const [x, y] of p[0]) {
    box[0] = Math.min(box[0], x); box[1] = Math.min(box[1], y); box[2] = Math.max(box[2], x); box[3] = Math.max(box[3], y);
  }
  return box;
}

// ---- the display state: what every tile should show ------------------------------------------
function nearestBand(feature, nm) {
  const wl = feature.properties.wavelength;
  if (!wl) return Math.max(0, Math.min(feature.properties.bands - 1, Math.round(nm)));
  let best = 0;
  for (let i = 1; i < wl.length; i++) if (Math.abs(wl[i] - nm) < Math.abs(wl[best] - nm)) best = i;
  return best;
}
function channelsNm() {
  if ($("display").value === "grey") return [Number($("band-grey").value)];
  return ["band-r", "band-g", "band-b"].map((id) => Number($(id).value));
}
const visibleFlights = () => viewer.order.filter((id) => !viewer.hidden.has(id) && viewer.byId.has(id));
// the flight whose bands and statistics the display controls use: the open one, else the earliest shown
const referenceFlight = () => viewer.open ||
  (viewer.features.find((f) => !viewer.hidden.has(f.id)) || viewer.features[0] || { id: null }).id;

// the request parameters of one flight's values (everything but the bands)
function flightParams(id, preview) {
  const q = new URLSearchParams();
  q.set("mode", $("mode").value || "radiance");
  q.set("overlap", $("overlap").value);
  const p = viewer.params[id];
  if (p) {
    if (p.cubes) q.set("cubes", `${p.cubes[0] - 1}-${p.cubes[1] - 1}`);
    const ground = preview && preview.ground !== undefined ? preview.ground : p.ground;
    const sync = preview && preview.sync !== undefined ? preview.sync : p.sync;
    if (ground !== null && ground !== undefined) q.set("ground_height", String(ground));
    if (sync !== null && sync !== undefined) q.set("sync_offset", String(sync));
  }
  return q.toString();
}

let preview = null;          // {ground|sync: value} while a slider of the open flight is dragged
function buildSpec() {
  const nm = channelsNm();
  const flights = visibleFlights().map((id) => {
    const f = viewer.byId.get(id);
    const coarse = preview && id === viewer.open;
    return { id, params: flightParams(id, coarse ? preview : null), bands: nm.map((w) => nearestBand(f, w)),
             up: coarse ? PREVIEW_UP : 0, box: flightBox(id, coarse) };
  });
  const ranges = stretchRanges(nm);
  const nadir = $("overlap").value === "nadir";
  const data = JSON.stringify(flights.map((f) => [f.id, f.params, f.bands, f.up]));
  return { flights, nm, ranges, nadir, data, id: data + JSON.stringify(ranges) + nadir, grey: nm.length === 1 };
}

// a flight's box (lon/lat), padded: by half its size while its footprint may have moved (a new
// ground height, sync offset or cube range whose outline has not arrived, a slider preview), else
// by a tenth (the outline samples the meshes' edges): tiles outside it are not asked for
function flightBox(id, moving) {
  const f = viewer.byId.get(id);
  const o = viewer.outlines[id];
  const known = !moving && (o ? o.params === outlineParams(id) : !viewer.params[id]);
  const b = geometryBox((o && o.geometry) || f.geometry);
  const pad = known ? 0.1 : 0.5;
  const dx = (b[2] - b[0]) * pad + 1e-4, dy = (b[3] - b[1]) * pad + 1e-4;
  return [b[0] - dx, b[1] - dy, b[2] + dx, b[3] + dy];
}
// the parameters an outline depends on (not the mode or overlap rule)
function outlineParams(id) {
  const q = new URLSearchParams(flightParams(id, null));
  q.delete("mode"); q.delete("overlap");
  return q.toString();
}
viewer.outlines = {};

// ---- band planes: fetched per tile and flight, cached, shared by every band choice -------------
const cache = new Map();     // entry key -> {planes: Map(band -> Float32Array), key, empty, side, bytes}
let cacheBytes = 0;
viewer.clearCache = () => { cache.clear(); cacheBytes = 0; statsCache.clear(); };
const inflight = new Map();  // request key -> {controller, entry, bands}

// the tile whose values a shown tile uses: itself, or for a preview its ancestor f.up zooms up
function entryCoords(f, c) {
  const up = Math.min(f.up || 0, c.z);
  return { z: c.z - up, x: c.x >> up, y: c.y >> up, up };
}
function entryKey(f, coords) { const c = entryCoords(f, coords); return `${f.id}|${f.params}|${c.z}/${c.x}/${c.y}`; }
function entryOf(key) {
  let e = cache.get(key);
  if (e) { cache.delete(key); cache.set(key, e); return e; }   // most recently used last
  e = { planes: new Map(), key: null, empty: false, side: TILE, win: null, bytes: 0 };
  cache.set(key, e);
  return e;
}
function trimCache() {
  for (const [k, e] of cache) {
    if (cacheBytes <= CACHE_BYTES) break;
    cacheBytes -= e.bytes;
    cache.delete(k);
  }
}
function entryReady(e, f, nadir) {
  if (!e) return false;
  if (e.empty) return true;
  return f.bands.every((b) => e.planes.has(b)) && (!nadir || e.key !== null);
}

// what a tile's entry still lacks: null when it is ready or already asked, else {ek, e, bands, rk}
function missingOf(tile, f, spec) {
  const ek = entryKey(f, tile.coords);
  const e = entryOf(ek);
  if (entryReady(e, f, spec.nadir)) return null;
  const missing = [...new Set(f.bands)].filter((b) => !e.planes.has(b));
  const bands = missing.length ? missing : f.bands.slice(0, 1);
  const rk = `${ek}|${spec.nadir}|${bands}`;
  for (const [k, r] of inflight) if (r.entry === ek && bands.every((b) => r.bands.includes(b)) && r.nadir === spec.nadir) return null;
  if (inflight.has(rk)) return null;
  return { ek, e, bands, rk };
}

// keep the values of one answer (the window of the tile that holds values: column, row, width,
// height of the side x side tile; bands, then the key plane, float32 from offset bytes of buffer)
function keep(e, bands, buffer, offset, bytes, side, win, keyed) {
  win = win || [0, 0, side, side];
  if (e.win && (e.win.join() !== win.join() || e.side !== side)) { e.planes.clear(); e.key = null; }
  const n = win[2] * win[3];
  bands.forEach((b, i) => e.planes.set(b, new Float32Array(buffer, offset + i * n * 4, n)));
  if (keyed) e.key = new Float32Array(buffer, offset + bands.length * n * 4, n);
  e.side = side;
  e.win = win;
  e.bytes += bytes;
  cacheBytes += bytes;
  viewer.loads += 1;
}

async function refusal(response) {
  let body = null;
  try { body = await response.json(); } catch (err) { /* not JSON */ }
  return Object.assign(new Error((body && body.error) || `${response.status} ${response.statusText}`), { http: response.status });
}

function request(tile, f, spec) {
  const m = missingOf(tile, f, spec);
  if (!m) return;
  const { e, bands, rk } = m;
  const controller = new AbortController();
  inflight.set(rk, { controller, entry: m.ek, bands, nadir: spec.nadir, tile });
  const { z, x, y } = entryCoords(f, tile.coords);
  const url = `${idPath(f.id)}/values/${z}/${x}/${y}?bands=${bands.join(",")}&${f.params}&window=1`;
  viewer.requests += 1;
  busy();
  fetch(url, { signal: controller.signal, headers: generationHeaders() }).then(async (response) => {
    if (response.status === 204) { e.empty = true; return; }
    if (!response.ok) throw await refusal(response);
    const buffer = await response.arrayBuffer();
    const side = Number(response.headers.get("X-Side")) || TILE;
    const win = response.headers.get("X-Window");
    keep(e, bands, buffer, 0, buffer.byteLength, side, win && win.split(",").map(Number), !!response.headers.get("X-Key"));
    trimCache();
  }).catch((err) => {
    if (err.name === "AbortError") return;
    viewer.tileErrors += 1;
    failed(err.message, f.id);
  }).finally(() => {
    inflight.delete(rk);
    busy();
    schedule();
  });
}

// the flights drawn as ingested (no ground height, sync offset or cube range of their own, no
// slider preview): their tiles go BATCH at a time in one request of /api/values/batch, which answers
// them from the ingest's previews when zoomed out (issue 36: 100 flights, ~5 requests, not 110)
const batchable = (f, spec) => !spec.nadir && !f.up && !viewer.params[f.id];
function requestBatch(wanted, spec) {
  const parts = [];
  for (const [tile, f] of wanted) {
    const m = missingOf(tile, f, spec);
    if (!m || parts.some((p) => p.rk === m.rk)) continue;
    parts.push({ ...m, f, tile });
  }
  for (let i = 0; i < parts.length; i += BATCH) sendBatch(parts.slice(i, i + BATCH), spec);
}
function sendBatch(parts, spec) {
  if (parts.length === 1) { request(parts[0].tile, parts[0].f, spec); return; }
  const controller = new AbortController();
  for (const p of parts) inflight.set(p.rk, { controller, entry: p.ek, bands: p.bands, nadir: false, tile: p.tile, batch: parts });
  const q = new URLSearchParams(parts[0].f.params);
  q.set("parts", parts.map((p) => { const c = entryCoords(p.f, p.tile.coords); return `${p.f.id}/${c.z}/${c.x}/${c.y}/${p.bands.join(",")}`; }).join(";"));
  q.set("window", "1");
  viewer.requests += 1;
  busy();
  fetch(`/api/values/batch?${q}`, { signal: controller.signal, headers: generationHeaders() }).then(async (response) => {
    if (!response.ok) throw await refusal(response);
    const index = JSON.parse(response.headers.get("X-Parts") || "[]");
    const buffer = await response.arrayBuffer();
    let offset = 0;
    index.forEach(([status, bytes, side, win, keyed, error], i) => {
      const p = parts[i];
      if (status === 204) p.e.empty = true;
      else if (status === 200) keep(p.e, p.bands, buffer, offset, bytes, side, win, keyed);
      else { viewer.tileErrors += 1; failed(error || `${status}`, p.f.id); }
      offset += bytes;
    });
    trimCache();
  }).catch((err) => {
    if (err.name === "AbortError") return;
    viewer.tileErrors += 1;
    failed(err.message, parts[0].f.id);
  }).finally(() => {
    for (const p of parts) inflight.delete(p.rk);
    busy();
    schedule();
  });
}

// a request the server refused: say why next to the control, keep the picture, stop asking
let failedSpec = null;
function failed(message, id) {
  failedSpec = current ? current.id : null;
  showError(message);
  if (id !== viewer.open) status(`${id}: ${message}`, true);
}

function busy() {
  viewer.pending = inflight.size;
  $("busy").hidden = inflight.size === 0;
  $("busy-text").textContent = inflight.size ? ` ${inflight.size}` : "";
}

// ---- the layer: canvases that keep their picture until the replacement is complete -----------
const tiles = new Map();     // "z/x/y" -> {el, coords, shown: spec id | null}
let current = null;          // the spec every tile should show

const ValuesLayer = L.GridLayer.extend({
  createTile(coords) {
    const el = L.DomUtil.create("canvas", "values-tile");
    el.width = el.height = TILE;
    const tile = { el, coords: { z: coords.z, x: coords.x, y: coords.y }, shown: null };
    const tb = tileBounds(coords.z, coords.x, coords.y);
    if (current && current.flights.some((f) => boxesMeet(f.box, tb))) el.classList.add("placeholder");
    tiles.set(`${coords.z}/${coords.x}/${coords.y}`, tile);
    viewer.settled = viewer.ready = false;
    schedule();
    return el;
  },
});
const layer = new ValuesLayer({ maxZoom: 24, tileSize: TILE, keepBuffer: 1, updateWhenZooming: false,
                                className: "flight-tiles" });
layer.on("tileunload", (ev) => {
  const key = `${ev.coords.z}/${ev.coords.x}/${ev.coords.y}`;
  const tile = tiles.get(key);
  tiles.delete(key);
  for (const [k, r] of inflight) if (r.tile === tile && !r.batch) { r.controller.abort(); inflight.delete(k); }
  busy();
});
layer.addTo(map);

// the tiles of the current zoom, those nearest the centre of the view first (asked for first)
function liveTiles() {
  const z = Math.round(map.getZoom());
  const c = map.project(map.getCenter(), z).divideBy(TILE);
  const d = (t) => (t.coords.x + 0.5 - c.x) ** 2 + (t.coords.y + 0.5 - c.y) ** 2;
  return [...tiles.values()].filter((t) => t.coords.z === z).sort((a, b) => d(a) - d(b));
}

function tileReady(tile, spec) {
  const tb = tileBounds(tile.coords.z, tile.coords.x, tile.coords.y);
  return spec.flights.every((f) => !boxesMeet(f.box, tb) || entryReady(cache.get(entryKey(f, tile.coords)), f, spec.nadir));
}

function schedule() {
  if (scheduled) return;
  scheduled = true;
  requestAnimationFrame(() => { scheduled = false; pump(); });
}

// ask for what is missing; draw new tiles as they complete, swap the others all at once
function pump() {
  const spec = current;
  if (!spec) return;
  if (!spec.ranges) { ensureRanges(spec); }
  const live = liveTiles();
  let complete = true;
  const wanted = new Map();   // entry key -> the bands the current view needs of it
  const batch = [];           // [tile, flight] asked together (requestBatch)
  for (const tile of live) {
    if (tile.shown === spec.id) continue;
    const tb = tileBounds(tile.coords.z, tile.coords.x, tile.coords.y);
    let ready = true;
    for (const f of spec.flights) {
      if (!boxesMeet(f.box, tb)) continue;
      const ek = entryKey(f, tile.coords);
      if (!wanted.has(ek)) wanted.set(ek, new Set());
      for (const b of f.bands) wanted.get(ek).add(b);
      if (!entryReady(cache.get(ek), f, spec.nadir)) {
        ready = false;
        if (failedSpec !== spec.id) {
          if (batchable(f, spec)) batch.push([tile, f]); else request(tile, f, spec);
        }
      }
    }
    if (ready && spec.ranges && tile.shown === null) draw(tile, spec);   // nothing to keep: show it now
    if (!ready) complete = false;
  }
  requestBatch(batch, spec);
  // requests for a picture nobody waits for any more (an older ground height or band, a tile gone);
  // a batch goes when none of its parts is waited for
  const unwanted = (q) => { const w = wanted.get(q.entry || q.ek); return !w || !q.bands.some((b) => w.has(b)); };
  for (const [k, r] of inflight) {
    if (r.batch ? r.batch.every(unwanted) : unwanted(r)) { r.controller.abort(); inflight.delete(k); }
  }
  busy();
  if (complete && spec.ranges) {
    for (const tile of live) if (tile.shown !== spec.id) draw(tile, spec);
    if (spec.flights.length || !live.length) settle(spec);
  } else {
    viewer.settled = viewer.ready = false;
  }
}

function settle(spec) {
  const was = viewer.settled;
  viewer.settled = viewer.ready = inflight.size === 0;
  if (viewer.settled && !was) {
    viewer.settledAt = performance.now();    // the bench: time to a full screen
    if (preview) viewer.previews += 1;
  }
  if (viewer.settled) clearErrors("err-cubes", "err-ground", "err-sync", "err-mode", "err-bands");
  viewer.specId = spec.id;
  if (preview && previewNext !== null) { startPreview(previewNext); }
  if ($("stretch").value === "view" && !spec.viewStretchFresh) {
    spec.viewStretchFresh = true;
    const r = viewRanges(spec);
    if (r && JSON.stringify(r) !== JSON.stringify(viewStretch)) { viewStretch = r; refresh(); }
  }
}

// one tile's picture from the planes of every flight over it (later flights on top, or the one
// seen closest to nadir), stretched here
let image = null;
function draw(tile, spec) {
  const ctx = tile.el.getContext("2d");
  if (!image) image = ctx.createImageData(TILE, TILE);
  const d = image.data;
  d.fill(0);
  const best = spec.nadir ? new Float32Array(TILE * TILE).fill(Infinity) : null;
  const tb = tileBounds(tile.coords.z, tile.coords.x, tile.coords.y);
  const k = spec.flights.length ? spec.flights[0].bands.length : 0;
  const lo = spec.ranges ? spec.ranges.map((r) => r[0]) : [0, 0, 0];
  const sc = spec.ranges ? spec.ranges.map((r) => 255 / (r[1] - r[0])) : [0, 0, 0];
  for (const f of spec.flights) {
    if (!boxesMeet(f.box, tb)) continue;
    const e = cache.get(entryKey(f, tile.coords));
    if (!e || e.empty) continue;
    // an ancestor's values (previews): this tile's part of it, each value over 2^shift pixels; the
    // planes hold the window [c0, c0 + w) x [r0, r0 + h) of the n x n values
    const up = entryCoords(f, tile.coords).up, n = e.side, shift = Math.log2(TILE / n) + up, mask = (1 << up) - 1;
    const ox = (tile.coords.x & mask) * (n >> up), oy = (tile.coords.y & mask) * (n >> up);
    const [c0w, r0w, w, h] = e.win || [0, 0, n, n];
    const i0 = Math.max(0, (r0w - oy) << shift), i1 = Math.min(TILE, (r0w + h - oy) << shift);
    const j0 = Math.max(0, (c0w - ox) << shift), j1 = Math.min(TILE, (c0w + w - ox) << shift);
    const c0 = e.planes.get(f.bands[0]), c1 = e.planes.get(f.bands[k > 1 ? 1 : 0]), c2 = e.planes.get(f.bands[k > 1 ? 2 : 0]);
    const key = e.key;
    const l0 = lo[0], l1 = lo[k > 1 ? 1 : 0], l2 = lo[k > 1 ? 2 : 0];
    const s0 = sc[0], s1 = sc[k > 1 ? 1 : 0], s2 = sc[k > 1 ? 2 : 0];
    for (let i = i0; i < i1; i++) {
      const row = (oy + (i >> shift) - r0w) * w + ox - c0w;
      for (let j = j0; j < j1; j++) {
        const s = row + (j >> shift);
        const v0 = c0[s], v1 = c1[s], v2 = c2[s];
        if (v0 !== v0 || v1 !== v1 || v2 !== v2) continue;    // NaN: no line covers it
        const p = i * TILE + j;
        if (best) { const kv = key[s]; if (!(kv <= best[p])) continue; best[p] = kv; }
        const o = p * 4;
        d[o] = (v0 - l0) * s0 + 0.5; d[o + 1] = (v1 - l1) * s1 + 0.5; d[o + 2] = (v2 - l2) * s2 + 0.5; d[o + 3] = 255;
      }
    }
  }
  ctx.putImageData(image, 0, 0);
  tile.el.classList.remove("placeholder");
  tile.shown = spec.id;
  viewer.draws += 1;
}

// ---- stretch: computed here from the flight's statistics, the view's values or the user's ----
const statsCache = new Map();    // flight params + bands + percentiles -> {low, high}
let viewStretch = null;
function stretchRanges(nm) {
  const kind = $("stretch").value;
  const per = $("per-channel").checked && nm.length === 3;
  let pairs = null;
  if (kind === "manual") {
    const lo = Number($("stretch-low").value), hi = Number($("stretch-high").value);
    if (!(isFinite(lo) && isFinite(hi) && hi > lo) || $("stretch-low").value === "" || $("stretch-high").value === "") {
      showError("stretch: give LOW < HIGH", "err-stretch");
      return lastRanges;
    }
    clearErrors("err-stretch");
    return nm.map(() => [lo, hi]);
  }
  clearErrors("err-stretch");
  if (kind === "view") {
    pairs = viewStretch && viewStretch.length === nm.length ? viewStretch : null;
    if (!pairs) return lastRanges && lastRanges.length === nm.length ? lastRanges : null;
  } else {
    const id = referenceFlight();
    if (!id) return null;
    const f = viewer.byId.get(id);
    const st = statsCache.get(statsKey(id, nm.map((w) => nearestBand(f, w)), kind));
    if (!st) return null;
    pairs = st.low.map((l, i) => [l === null ? 0 : l, st.high[i] === null ? 1 : st.high[i]]);
    if (kind === "unscaled") {
      const hi = Math.max(...pairs.map((p) => p[1]));
      return nm.map(() => [0, hi > 0 ? hi : 1]);
    }
  }
  pairs = pairs.map(([l, h]) => [l, h > l ? h : l + 1]);
  if (!per) {
    const l = Math.min(...pairs.map((p) => p[0])), h = Math.max(...pairs.map((p) => p[1]));
    pairs = pairs.map(() => [l, h]);
  }
  return pairs;
}
let lastRanges = null;
// the whole flight's statistics depend on the mode and cube range, not on where its pixels land:
// a ground-height or sync change keeps its stretch (and asks nothing)
function statsParams(id) {
  const q = new URLSearchParams(flightParams(id, null));
  for (const name of ["ground_height", "sync_offset", "overlap"]) q.delete(name);
  return q.toString();
}
const statsKey = (id, bands, kind) => `${id}|${statsParams(id)}|${bands}|${kind === "unscaled" ? "0,100" : "2,98"}`;
const statsPending = new Set();
function ensureRanges(spec) {
  const kind = $("stretch").value;
  if (kind === "view") { if (!viewStretch) { viewStretch = viewRanges(spec) || null; if (viewStretch) refresh(); } return; }
  if (kind === "manual") return;
  const id = referenceFlight();
  if (!id) return;
  const f = viewer.byId.get(id);
  const bands = spec.nm.map((w) => nearestBand(f, w));
  const key = statsKey(id, bands, kind);
  if (statsCache.has(key) || statsPending.has(key)) return;
  statsPending.add(key);
  getJSON(`${idPath(id)}/stats?bands=${bands.join(",")}&${statsParams(id)}&percentiles=${kind === "unscaled" ? "0,100" : "2,98"}`)
    .then((st) => { statsCache.set(key, st); refresh(); })
    .catch((err) => showError(err.message))
    .finally(() => statsPending.delete(key));
}

// 2 %/98 % of the values the view shows (loaded planes of the tiles in view, subsampled to at most
// VIEW_SAMPLES pixels: a stretch change stays a few milliseconds whatever the window's size)
const VIEW_SAMPLES = 40000;
function viewRanges(spec) {
  const b = map.getBounds();
  const view = [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()];
  const k = spec.nm.length;
  const sources = [];
  let total = 0;
  for (const tile of liveTiles()) {
    const tb = tileBounds(tile.coords.z, tile.coords.x, tile.coords.y);
    if (!boxesMeet(tb, view)) continue;
    for (const f of spec.flights) {
      const e = cache.get(entryKey(f, tile.coords));
      if (!e || e.empty || !f.bands.every((band) => e.planes.has(band))) continue;
      const planes = f.bands.map((band) => e.planes.get(band));
      sources.push(planes);
      total += planes[0].length;
    }
  }
  if (!total) return null;
  const step = Math.max(1, Math.ceil(total / VIEW_SAMPLES));
  const samples = Array.from({ length: k }, () => new Float32Array(Math.ceil(total / step) + sources.length));
  let n = 0, offset = 0;
  for (const planes of sources) {
    const len = planes[0].length;
    for (let s = (step - (offset % step)) % step; s < len; s += step) {
      let finite = true;
      for (let c = 0; c < k; c++) { const v = planes[c][s]; if (v !== v) { finite = false; break; } }
      if (!finite) continue;
      for (let c = 0; c < k; c++) samples[c][n] = planes[c][s];
      n += 1;
    }
    offset += len;
  }
  if (!n) return null;
  return samples.map((v) => {
    const sorted = v.subarray(0, n).sort();
    const at = (q) => sorted[Math.min(n - 1, Math.max(0, Math.round((q / 100) * (n - 1))))];
    return [at(2), at(98)];
  });
}

// ---- changes ---------------------------------------------------------------------------------
function refresh() {
  // before the first view is set (the hash's, else the fit of every footprint) nothing is asked for:
  // the world view's tiles would be thrown away at once
  if (!viewer.booted) return;
  const spec = buildSpec();
  if (spec.ranges) lastRanges = spec.ranges;   // else new statistics are coming: draw when they arrive
  if (!current || spec.id !== current.id) { failedSpec = null; newGeneration(); }
  current = spec;
  // grey placeholders from the first frame: tiles made before the first view was known (the boot's
  // fit) get theirs here
  for (const t of tiles.values()) {
    const tb = tileBounds(t.coords.z, t.coords.x, t.coords.y);
    if (t.shown === null && spec.flights.some((f) => boxesMeet(f.box, tb))) t.el.classList.add("placeholder");
  }
  viewer.ready = viewer.settled = false;
  showOutputs();
  writeHash();
  pump();
}

// ---- the catalog: every flight matching the filters, on the map and in the list ---------------
let footprints = null;
async function loadCatalog(fit) {
  const q = new URLSearchParams();
  const b = map.getBounds();
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));
  if ($("f-inview").checked) q.set("bbox", [clamp(b.getWest(), -180, 180), clamp(b.getSouth(), -85, 85),
                                             clamp(b.getEast(), -180, 180), clamp(b.getNorth(), -85, 85)].map((v) => v.toFixed(7)).join(","));
  if ($("f-datetime").value.trim()) q.set("datetime", $("f-datetime").value.trim());
  if ($("f-wavelength").value.trim()) q.set("wavelength", $("f-wavelength").value.trim());
  let fc;
  try { fc = await getJSON(`/api/collections?${q}`); } catch (e) { showError(e.message, "err-filters"); return; }
  clearErrors("err-filters");
  viewer.features = fc.features;
  viewer.byId = new Map(fc.features.map((f) => [f.id, f]));
  const known = viewer.order.filter((id) => viewer.byId.has(id));
  viewer.order = known.concat(fc.features.map((f) => f.id).filter((id) => !known.includes(id)));
  if (viewer.open && !viewer.byId.has(viewer.open)) closeFlight();
  fillBandOptions();
  drawFootprints();
  renderList();
  status(`${fc.features.length} flight(s)`);
  if (fit && fc.features.length && !hashHasMap) map.fitBounds(footprints.getBounds(), { padding: [20, 20] });
  refresh();
}

function drawFootprints() {
  if (footprints) footprints.remove();
  const features = visibleFlights().map((id) => {
    const f = viewer.byId.get(id);
    return viewer.outlines[id] ? { ...f, geometry: viewer.outlines[id].geometry } : f;
  });
  footprints = L.geoJSON({ type: "FeatureCollection", features }, {
    pane: "footprints", interactive: false,
    style: (f) => ({ color: f.id === viewer.open ? "#ff3366" : "#ffcc33", weight: f.id === viewer.open ? 2.5 : 1.5,
                     fill: false, fillRule: "nonzero" }),
  });
  if ($("show-footprints").checked) footprints.addTo(map);
  viewer.footprints = footprints;
  placeLabels();
}

// footprint labels where there is room: the open flight's first, then the topmost; a label is shown
// only inside the map, over a footprint at least half its width on screen, and clear of every label
// already placed (an archive zoomed out is imagery, not a wall of names)
let labels = null;
const labelFont = document.createElement("canvas").getContext("2d");
function placeLabels() {
  if (labels) labels.remove();
  labels = L.layerGroup();
  viewer.labels = [];
  if (!footprints || !$("show-footprints").checked) return;
  labelFont.font = "10px system-ui, sans-serif";
  const size = map.getSize(), placed = [];
  const ids = visibleFlights().reverse();
  if (viewer.open && ids.includes(viewer.open)) ids.unshift(...ids.splice(ids.indexOf(viewer.open), 1));
  for (const id of ids) {
    const g = (viewer.outlines[id] && viewer.outlines[id].geometry) || viewer.byId.get(id).geometry;
    const [w, s, e, n] = geometryBox(g);
    const a = map.latLngToContainerPoint([n, w]), b = map.latLngToContainerPoint([s, e]);
    const c = map.latLngToContainerPoint([(s + n) / 2, (w + e) / 2]);
    const width = labelFont.measureText(id).width + 8, height = 15;
    if (Math.abs(b.x - a.x) < width / 2 || c.x < 0 || c.y < 0 || c.x > size.x || c.y > size.y) continue;
    const box = [c.x - width / 2 - 2, c.y - height / 2 - 2, c.x + width / 2 + 2, c.y + height / 2 + 2];
    if (placed.some((p) => box[0] < p[2] && p[0] < box[2] && box[1] < p[3] && p[1] < box[3])) continue;
    placed.push(box);
    viewer.labels.push(id);
    labels.addLayer(L.tooltip({ permanent: true, direction: "center", className: "footprint-label", opacity: 0.85,
                                interactive: false }).setLatLng(map.containerPointToLatLng(c)).setContent(id));
  }
  labels.addTo(map);
}
map.on("zoomend moveend resize", () => placeLabels());

function renderList() {
  const list = $("flights");
  list.replaceChildren();
  viewer.order.forEach((id, i) => {
    const f = viewer.byId.get(id);
    const p = f.properties;
    const li = document.createElement("li");
    li.dataset.id = id;
    li.classList.toggle("open", id === viewer.open);
    const show = document.createElement("input");
    show.type = "checkbox";
    show.checked = !viewer.hidden.has(id);
    show.setAttribute("aria-label", `draw ${id}`);
    show.addEventListener("change", () => { if (show.checked) viewer.hidden.delete(id); else viewer.hidden.add(id); drawFootprints(); refresh(); });
    const open = document.createElement("button");
    open.type = "button";
    open.className = "flight-open";
    open.textContent = id;
    open.title = `open ${id} (its controls, spectra)`;
    open.addEventListener("click", () => openFlight(id, true));
    const meta = document.createElement("span");
    meta.className = "meta";
    meta.textContent = `${p.start_datetime.slice(0, 19).replace("T", " ")} UTC · ${p.bands} bands ` +
      `${fmt(p.min_wavelength, 4)}–${fmt(p.max_wavelength, 4)} nm · ${p.cubes ?? "?"} cubes · ${fmt(p.gsd, 2)} m`;
    const move = (delta, label, text) => {
      const b = document.createElement("button");
      b.type = "button"; b.className = "move"; b.textContent = text; b.title = label; b.setAttribute("aria-label", `${label}: ${id}`);
      b.disabled = i + delta < 0 || i + delta >= viewer.order.length;
      b.addEventListener("click", () => {
        const o = viewer.order;
        [o[i], o[i + delta]] = [o[i + delta], o[i]];
        renderList(); drawFootprints(); refresh();
        const again = $("flights").querySelector(`li[data-id="${CSS.escape(id)}"] button.move[title="${label}"]`);
        if (again && !again.disabled) again.focus();
      });
      return b;
    };
    li.append(show, open, move(-1, "draw under", "▲"), move(1, "draw over", "▼"), meta);
    list.append(li);
  });
}

$("filters").addEventListener("submit", (ev) => { ev.preventDefault(); loadCatalog(false); });
$("show-footprints").addEventListener("change", () => drawFootprints());
$("overlap").addEventListener("change", () => refresh());

// ---- bands -----------------------------------------------------------------------------------
function fillBandOptions() {
  const id = referenceFlight();
  if (!id) return;
  const p = viewer.byId.get(id).properties;
  const keep = ["band-r", "band-g", "band-b", "band-grey"].map((s) => $(s).value);
  for (const sel of ["band-r", "band-g", "band-b", "band-grey"]) {
    const select = $(sel);
    select.replaceChildren();
    for (let i = 0; i < p.bands; i++) {
      const o = document.createElement("option");
      o.value = p.wavelength ? String(p.wavelength[i]) : String(i);
      o.textContent = p.wavelength ? `${i + 1}: ${p.wavelength[i].toFixed(1)} nm` : `band ${i + 1}`;
      select.append(o);
    }
  }
  if (keep[0] === "") setTrueColour(false);
  else ["band-r", "band-g", "band-b", "band-grey"].forEach((s, i) => selectNearest($(s), Number(keep[i])));
  if (!$("mode").options.length) setModes(["raw", "relative", "radiance"], "radiance");
}
function selectNearest(select, nm) {
  let best = null;
  for (const o of select.options) if (best === null || Math.abs(Number(o.value) - nm) < Math.abs(Number(best.value) - nm)) best = o;
  if (best) select.value = best.value;
}
function setTrueColour(apply = true) {
  const id = referenceFlight();
  const p = id && viewer.byId.get(id).properties;
  if (!p) return;
  if (p.wavelength && p.min_wavelength <= 640 && p.max_wavelength >= 460) {
    [640, 550, 460].forEach((nm, i) => selectNearest($(["band-r", "band-g", "band-b"][i]), nm));
  } else {
    const n = p.bands, pick = (i) => $(["band-r", "band-g", "band-b"][i]).options[i === 0 ? (3 * n) >> 2 : i === 1 ? n >> 1 : n >> 2];
    [0, 1, 2].forEach((i) => { $(["band-r", "band-g", "band-b"][i]).value = pick(i).value; });
  }
  $("band-grey").value = $("band-r").value;
  if (apply) { $("display").value = "rgb"; showDisplay(); refresh(); }
}
function setModes(modes, chosen) {
  const mode = $("mode");
  const keep = mode.value;
  mode.replaceChildren(...modes.map((m) => { const o = document.createElement("option"); o.value = m; o.textContent = m; return o; }));
  mode.value = modes.includes(keep) ? keep : chosen;
}
function showDisplay() {
  const grey = $("display").value === "grey";
  for (const el of document.querySelectorAll(".row.rgb")) el.hidden = grey;
  for (const el of document.querySelectorAll(".row.grey")) el.hidden = !grey;
  $("per-channel-label").hidden = grey;
  document.querySelector(".row.manual").hidden = $("stretch").value !== "manual";
}

for (const id of ["band-r", "band-g", "band-b", "band-grey"]) $(id).addEventListener("change", () => refresh());
$("display").addEventListener("change", () => { showDisplay(); refresh(); });
$("mode").addEventListener("change", () => refresh());
$("truecolour").addEventListener("click", () => setTrueColour(true));
$("stretch").addEventListener("change", () => {
  if ($("stretch").value === "view") viewStretch = current ? viewRanges(current) : null;
  if ($("stretch").value === "manual" && $("stretch-low").value === "" && lastRanges) {
    $("stretch-low").value = Number(Math.min(...lastRanges.map((r) => r[0])).toPrecision(5));
    $("stretch-high").value = Number(Math.max(...lastRanges.map((r) => r[1])).toPrecision(5));
  }
  showDisplay(); refresh();
});
for (const id of ["per-channel", "stretch-low", "stretch-high"]) $(id).addEventListener("change", () => refresh());
map.on("movestart zoomstart", () => { viewer.settled = viewer.ready = false; });
map.on("moveend", () => {
  newGeneration();
  if ($("stretch").value === "view" && current) { current.viewStretchFresh = false; }
  writeHash();
  schedule();
});

function showOutputs() {
  if (viewer.open && viewer.params[viewer.open]) {
    const p = viewer.params[viewer.open];
    const g = preview && preview.ground !== undefined ? preview.ground : p.ground;
    const s = preview && preview.sync !== undefined ? preview.sync : p.sync;
    $("ground-out").textContent = `${Number(g).toFixed(1)} m`;
    $("sync-out").textContent = `${Number(s).toFixed(3)} s`;
  }
  const r = current && current.ranges;
  const names = $("display").value === "grey" ? ["grey"] : ["R", "G", "B"];
  $("stretch-values").textContent = r ? r.map(([lo, hi], i) => `${names[i]} ${fmt(lo)}…${fmt(hi)}`).join("  ") : "";
}

// ---- the open flight: its controls, footprint and spectra -----------------------------------
async function openFlight(id, fit) {
  status(`opening ${id}…`);
  let info;
  try { info = await getJSON(idPath(id)); } catch (e) { status(e.message, true); return; }
  viewer.open = id;
  viewer.info = info;
  viewer.hidden.delete(id);
  if (!viewer.params[id]) viewer.params[id] = { cubes: null, ground: info.ground_height, sync: info.sync_offset };
  $("flight-title").textContent = id;
  setModes(info.modes, info.default_mode);
  fillBandOptions();
  setSliders(info);
  $("controls").hidden = false;
  renderList();
  if (fit) map.fitBounds(L.geoJSON(viewer.byId.get(id)).getBounds(), { padding: [30, 30] });
  status(`${id}: ${info.cubes.length} cubes, ${info.bands} bands`);
  loadOutline(id);
  drawFootprints();
  refresh();
}

function setSliders(info) {
  const p = viewer.params[info.id];
  const gh = info.ground_height;
  const ground = $("ground");
  // over a DEM (a collection ingested with --dem) the slider is the DEM's vertical offset
  document.querySelector('label[for="ground"]').textContent = info.terrain ? "DEM offset" : "Ground";
  ground.title = info.terrain ? `vertical offset of ${info.terrain.dem}, metres` : "flat ground height, metres";
  ground.min = (gh - (info.terrain ? 10 : 30)).toFixed(1);
  ground.max = (info.terrain ? gh + 10 : Math.min(gh + 30, info.lowest_camera - 1.5)).toFixed(1);
  ground.value = p.ground;
  const sync = $("sync");
  sync.min = (info.sync_offset - 0.25).toFixed(3); sync.max = (info.sync_offset + 0.25).toFixed(3);
  sync.value = p.sync;
  const n = info.cubes.length;
  for (const el of [$("cube-first"), $("cube-last")]) { el.min = 1; el.max = n; }
  $("cube-first").value = p.cubes ? p.cubes[0] : 1;
  $("cube-last").value = p.cubes ? p.cubes[1] : n;
  $("cube-first").title = `first cube (${info.cubes[0].base} is 1)`;
}

function closeFlight() {
  viewer.open = viewer.info = null;
  $("controls").hidden = true;
  renderList();
  drawFootprints();
  refresh();
}

async function loadOutline(id) {
  const q = outlineParams(id);
  try {
    const geometry = await getJSON(`${idPath(id)}/outline?${q}`);
    if (geometry.coordinates.length) viewer.outlines[id] = { geometry, params: q };
    drawFootprints();
    refresh();
  } catch (e) { /* the tiles say what is wrong */ }
}

// an error message stays until the view it refused is replaced (settle) or Reset: clearing it on
// input would move the controls under the pointer
// the outline is asked first: its meshes are the ones the tiles need, and once it has arrived the
// tiles beyond the new footprint are no longer asked for
function flightChanged() {
  if (viewer.open) loadOutline(viewer.open);
  refresh();
}
function cubesInput() {
  const p = viewer.params[viewer.open];
  const n = viewer.info.cubes.length;
  const a = Math.round(Number($("cube-first").value)), b = Math.round(Number($("cube-last").value));
  p.cubes = a === 1 && b === n ? null : [a, b];
  flightChanged();
}
$("cube-first").addEventListener("change", cubesInput);
$("cube-last").addEventListener("change", cubesInput);

// sliders: a coarse preview (64 x 64 tiles of the open flight) while dragging, one at a time, at
// the latest value; the full resolution on release. A preview starts at the next animation frame:
// a click on the slider's track (input and change at once) asks for no preview nobody would see
let previewNext = null, previewFrame = null;
function startPreview(value) {
  previewNext = null;
  preview = value;
  refresh();
}
for (const [id, name] of [["ground", "ground"], ["sync", "sync"]]) {
  $(id).addEventListener("input", () => {
    previewNext = { [name]: Number($(id).value) };
    showOutputsValue(name, previewNext[name]);
    if ((preview && !viewer.settled) || previewFrame !== null) return;   // the settled preview starts the next
    previewFrame = requestAnimationFrame(() => {
      previewFrame = null;
      if (previewNext !== null) startPreview(previewNext);
    });
  });
  $(id).addEventListener("change", () => {
    preview = null; previewNext = null;
    viewer.params[viewer.open][name] = Number($(id).value);
    flightChanged();
  });
}
function showOutputsValue(name, v) {
  if (name === "ground") $("ground-out").textContent = `${v.toFixed(1)} m`;
  else $("sync-out").textContent = `${v.toFixed(3)} s`;
}

$("reset").addEventListener("click", () => {
  const info = viewer.info;
  viewer.params[info.id] = { cubes: null, ground: info.ground_height, sync: info.sync_offset };
  setSliders(info);
  setModes(info.modes, info.default_mode);
  $("mode").value = info.default_mode;
  $("stretch").value = "flight";
  $("per-channel").checked = true;
  setTrueColour(false);
  $("display").value = "rgb";
  showDisplay();
  clearErrors();
  failedSpec = null;
  flightChanged();
});
$("close").addEventListener("click", () => { closeFlight(); status(""); });

// ---- clicks: open the flight under the pointer, or pin the open flight's spectrum -------------
map.on("click", (ev) => {
  const { lng, lat } = ev.latlng;
  const under = visibleFlights().filter((id) => {
    const g = (viewer.outlines[id] && viewer.outlines[id].geometry) || viewer.byId.get(id).geometry;
    return inGeometry(lng, lat, g);
  });
  if (viewer.open && (under.includes(viewer.open) || !under.length)) { pinPoint(ev.latlng); return; }
  if (under.length) openFlight(under[under.length - 1], false);
});

// pinPoint, showPixel and the chart: spectra.js

// ---- the URL hash: the state of the page, shareable; editing it updates the view -------------
let hashHasMap = false;
let writing = false;
function hashState() {
  const c = map.getCenter();
  const s = new URLSearchParams();
  s.set("map", `${map.getZoom()}/${c.lat.toFixed(7)}/${c.lng.toFixed(7)}`);
  s.set("bands", channelsNm().map((v) => Number(v.toFixed(3))).join(","));
  if ($("mode").value) s.set("mode", $("mode").value);
  const kind = $("stretch").value;
  // a refused value (LOW >= HIGH, a cube range the flight does not have) is not shared: the last
  // accepted one is
  const lo = $("stretch-low").value, hi = $("stretch-high").value;
  if (kind === "manual" && lo !== "" && hi !== "" && isFinite(Number(lo)) && isFinite(Number(hi)) && Number(lo) < Number(hi)) {
    viewer.acceptedStretch = `${lo},${hi}`;
  }
  s.set("stretch", kind === "manual" ? (viewer.acceptedStretch || "p2,p98") : kind === "flight" ? "p2,p98" : kind);
  if (!$("per-channel").checked) s.set("shared", "1");
  if ($("overlap").value !== "last") s.set("overlap", $("overlap").value);
  if (viewer.open) {
    s.set("open", viewer.open);
    const p = viewer.params[viewer.open];
    if (p && viewer.info) {
      if (p.ground !== viewer.info.ground_height) s.set("ground", String(p.ground));
      if (p.sync !== viewer.info.sync_offset) s.set("sync", String(p.sync));
      const n = viewer.info.cubes.length;
      if (p.cubes && p.cubes.every(Number.isInteger) && 1 <= p.cubes[0] && p.cubes[0] <= p.cubes[1] && p.cubes[1] <= n) {
        s.set("cubes", `${p.cubes[0]}-${p.cubes[1]}`);
      }
    }
  }
  if (viewer.hidden.size || viewer.order.join() !== viewer.features.map((f) => f.id).join()) s.set("flights", visibleFlights().join(","));
  return s.toString().replace(/%2C/g, ",").replace(/%2F/g, "/").replace(/%7C/g, "|");
}
let hashTimer = null;
let booted = false;
function writeHash() {
  if (!booted) return;
  clearTimeout(hashTimer);
  hashTimer = setTimeout(() => {
    const h = "#" + hashState();
    if (location.hash !== h) { writing = true; history.replaceState(null, "", h); writing = false; }
    viewer.hash = h;
  }, 100);
}

async function applyHash(initial) {
  const s = new URLSearchParams(location.hash.slice(1));
  const m = (s.get("map") || "").split("/").map(Number);
  if (m.length === 3 && m.every(isFinite)) { map.setView([m[1], m[2]], m[0], { animate: false }); hashHasMap = true; }
  if (s.has("flights")) {
    const shown = s.get("flights").split(",").filter(Boolean);
    const all = viewer.features.map((f) => f.id);
    viewer.hidden = new Set(all.filter((id) => !shown.includes(id)));
    viewer.order = all.filter((id) => !shown.includes(id)).concat(shown.filter((id) => all.includes(id)));
  } else if (!initial) { viewer.hidden = new Set(); }
  if (s.has("overlap")) $("overlap").value = s.get("overlap"); else $("overlap").value = "last";
  const open = s.get("open");
  if (open && viewer.byId.has(open) && open !== viewer.open) await openFlight(open, false);
  else if (!open && viewer.open && !initial) closeFlight();
  if (s.has("mode") && [...$("mode").options].some((o) => o.value === s.get("mode"))) $("mode").value = s.get("mode");
  const bands = (s.get("bands") || "").split(",").filter((v) => v.trim() !== "").map(Number).filter(isFinite);
  if (bands.length === 1) { $("display").value = "grey"; selectNearest($("band-grey"), bands[0]); }
  if (bands.length === 3) { $("display").value = "rgb"; ["band-r", "band-g", "band-b"].forEach((id, i) => selectNearest($(id), bands[i])); }
  const st = s.get("stretch");
  if (st) {
    const parts = st.split(/[,|]/);
    if (st === "view" || st === "unscaled") $("stretch").value = st;
    else if (parts.length === 2 && parts.every((p) => /^p/i.test(p))) $("stretch").value = "flight";
    else if (parts.length === 2 && parts.every((p) => isFinite(Number(p)))) {
      $("stretch").value = "manual"; $("stretch-low").value = parts[0]; $("stretch-high").value = parts[1];
    }
  }
  $("per-channel").checked = s.get("shared") !== "1";
  if (viewer.open && viewer.info) {
    const p = viewer.params[viewer.open];
    if (s.has("ground") && isFinite(Number(s.get("ground")))) p.ground = Number(s.get("ground"));
    else if (!initial) p.ground = viewer.info.ground_height;
    if (s.has("sync") && isFinite(Number(s.get("sync")))) p.sync = Number(s.get("sync"));
    else if (!initial) p.sync = viewer.info.sync_offset;
    const c = (s.get("cubes") || "").split("-").map(Number);
    p.cubes = c.length === 2 && c.every(Number.isInteger) ? c : null;
    setSliders(viewer.info);
    loadOutline(viewer.open);
  }
  showDisplay();
  renderList();
  drawFootprints();
  refresh();
}
window.addEventListener("hashchange", () => { if (!writing) applyHash(false); });

// ---- keyboard and narrow screens ------------------------------------------------------------
$("panel-toggle").addEventListener("click", () => {
  const collapsed = document.body.classList.toggle("collapsed");
  $("panel-toggle").setAttribute("aria-expanded", String(!collapsed));
  setTimeout(() => map.invalidateSize(), 50);
});
if (window.matchMedia("(max-width: 720px)").matches) {
  document.body.classList.add("collapsed");
  $("panel-toggle").setAttribute("aria-expanded", "false");
}

(async () => {
  hashHasMap = false;
  await loadCatalog(false);
  const s = new URLSearchParams(location.hash.slice(1));
  if (location.hash.length > 1) await applyHash(true);
  if (!s.has("map") && footprints && viewer.features.length) map.fitBounds(footprints.getBounds(), { padding: [20, 20] });
  showDisplay();
  booted = viewer.booted = true;
  refresh();
})();
