// archive view: the tiles of the map, drawn from band-value tiles (float32 planes rendered by the
// server's inverse renderer) that this page stretches and composes itself, so stretch and R/G/B
// changes among loaded bands need no request; a change that needs new values keeps the previous
// picture until every tile in view has its replacement (double buffering).
//
// The spec (viewer.current, made by controls.js's refresh, which this module asks for with emit("refresh"):
// it imports nothing of controls.js): what every tile should show, {flights:
// [{id, params, bands, up, box}], nm, ranges, keyed, lowest, data, id, grey}; keyed: the values come
// with the overlap rule's per-pixel key plane; lowest: a pixel shows the flight of the lowest key,
// else the later flight. The stretch is computed here too: from the reference flight's statistics
// (asked once per flight, mode, cube range and bands), the view's values or the user's range.
import { boxesMeet, map, tileBounds } from "./map.js";
import { nearestBand, statsParams } from "./params.js";
import { $, BATCH, CACHE_BYTES, TILE, clearErrors, emit, generationHeaders, getJSON, idPath, referenceFlight, refusal, showError,
         status, viewer } from "./state.js";

let scheduled = false;      // a pump() is due at the next animation frame

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
function entryReady(e, f, keyed) {
  if (!e) return false;
  if (e.empty) return true;
  return f.bands.every((b) => e.planes.has(b)) && (!keyed || e.key !== null);
}

// the loaded planes of flight f over a tile ([band of f.bands] -> Float32Array), null if not all loaded
function loadedPlanes(tile, f) {
  const e = cache.get(entryKey(f, tile.coords));
  if (!e || e.empty || !f.bands.every((band) => e.planes.has(band))) return null;
  return f.bands.map((band) => e.planes.get(band));
}

// what a tile's entry still lacks: null when it is ready or already asked, else {ek, e, bands, rk}
function missingOf(tile, f, spec) {
  const ek = entryKey(f, tile.coords);
  const e = entryOf(ek);
  if (entryReady(e, f, spec.keyed)) return null;
  const missing = [...new Set(f.bands)].filter((b) => !e.planes.has(b));
  const bands = missing.length ? missing : f.bands.slice(0, 1);
  const rk = `${ek}|${spec.keyed}|${bands}`;
  for (const [, r] of inflight) if (r.entry === ek && bands.every((b) => r.bands.includes(b)) && r.keyed === spec.keyed) return null;
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

function request(tile, f, spec) {
  const m = missingOf(tile, f, spec);
  if (!m) return;
  const { e, bands, rk } = m;
  const controller = new AbortController();
  inflight.set(rk, { controller, entry: m.ek, bands, keyed: spec.keyed, tile });
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
// slider preview, no key plane): their tiles go BATCH at a time in one request of /api/values/batch,
// which answers them from the ingest's previews when zoomed out (issue 36: 100 flights, ~5 requests, not 110)
const batchable = (f, spec) => !spec.keyed && !f.up && !viewer.params[f.id];
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
  for (const p of parts) inflight.set(p.rk, { controller, entry: p.ek, bands: p.bands, keyed: false, tile: p.tile, batch: parts });
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
    index.forEach(([code, bytes, side, win, keyed, error], i) => {
      const p = parts[i];
      if (code === 204) p.e.empty = true;
      else if (code === 200) keep(p.e, p.bands, buffer, offset, bytes, side, win, keyed);
      else { viewer.tileErrors += 1; failed(error || `${code}`, p.f.id); }
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
function failed(message, id) {
  viewer.failedSpec = viewer.current ? viewer.current.id : null;
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

const ValuesLayer = L.GridLayer.extend({
  createTile(coords) {
    const el = L.DomUtil.create("canvas", "values-tile");
    el.width = el.height = TILE;
    const tile = { el, coords: { z: coords.z, x: coords.x, y: coords.y }, shown: null };
    const tb = tileBounds(coords.z, coords.x, coords.y);
    const spec = viewer.current;
    if (spec && spec.flights.some((f) => boxesMeet(f.box, tb))) el.classList.add("placeholder");
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

// grey placeholders on the tiles that show nothing yet where a flight of spec will be drawn (tiles
// made before the first view was known, the boot's fit, get theirs at the first refresh)
export function markPlaceholders(spec) {
  for (const t of tiles.values()) {
    const tb = tileBounds(t.coords.z, t.coords.x, t.coords.y);
    if (t.shown === null && spec.flights.some((f) => boxesMeet(f.box, tb))) t.el.classList.add("placeholder");
  }
}

export function schedule() {
  if (scheduled) return;
  scheduled = true;
  requestAnimationFrame(() => { scheduled = false; pump(); });
}

// ask for what is missing; draw new tiles as they complete, swap the others all at once
export function pump() {
  const spec = viewer.current;
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
      if (!entryReady(cache.get(ek), f, spec.keyed)) {
        ready = false;
        if (viewer.failedSpec !== spec.id) {
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
    if (viewer.preview) viewer.previews += 1;
  }
  if (viewer.settled) clearErrors("err-cubes", "err-ground", "err-sync", "err-mode", "err-bands");
  viewer.specId = spec.id;
  if (viewer.preview && viewer.previewNext !== null) { emit("preview", viewer.previewNext); }
  if ($("stretch").value === "view" && !spec.index && !spec.viewStretchFresh) {
    spec.viewStretchFresh = true;
    const r = viewRanges(spec);
    if (r && JSON.stringify(r) !== JSON.stringify(viewer.viewStretch)) { viewer.viewStretch = r; emit("refresh"); }
  }
}

// the index display's colour ramp from -1 to +1 (ColorBrewer's RdYlGn stops, as the legend's CSS
// gradient in app.css): RAMP_LUT[k] the colour of (k / 127.5 - 1)
export const RAMP_STOPS = [[-1, [165, 0, 38]], [-0.5, [244, 109, 67]], [0, [255, 255, 191]], [0.5, [102, 189, 99]],
                           [1, [0, 104, 55]]];
export function rampColour(v) {
  const x = Math.max(-1, Math.min(1, v));
  let k = 0;
  while (k < RAMP_STOPS.length - 2 && x > RAMP_STOPS[k + 1][0]) k++;
  const [x0, c0] = RAMP_STOPS[k], [x1, c1] = RAMP_STOPS[k + 1], t = (x - x0) / (x1 - x0);
  return c0.map((c, i) => Math.round(c + (c1[i] - c) * t));
}
const RAMP_LUT = Array.from({ length: 256 }, (_, k) => rampColour(k / 127.5 - 1));

// one tile's picture from the planes of every flight over it (later flights on top, or the one of
// the lowest key: the overlap rule's), stretched here
let image = null;
function draw(tile, spec) {
  const ctx = tile.el.getContext("2d");
  if (!image) image = ctx.createImageData(TILE, TILE);
  const d = image.data;
  d.fill(0);
  const best = spec.lowest ? new Float32Array(TILE * TILE).fill(Infinity) : null;
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
    const key = e.key;
    if (spec.index) {   // (a - b) / (a + b) of the two bands, on the index ramp
      const a = e.planes.get(f.bands[0]), b = e.planes.get(f.bands[1]);
      for (let i = i0; i < i1; i++) {
        const row = (oy + (i >> shift) - r0w) * w + ox - c0w;
        for (let j = j0; j < j1; j++) {
          const s = row + (j >> shift);
          const v = (a[s] - b[s]) / (a[s] + b[s]);
          if (v !== v || !isFinite(v)) continue;    // NaN: no line covers it (or a + b is 0)
          const p = i * TILE + j;
          if (best) { const kv = key[s]; if (!(kv <= best[p])) continue; best[p] = kv; }
          const o = p * 4, c = RAMP_LUT[Math.max(0, Math.min(255, Math.round((v + 1) * 127.5)))];
          d[o] = c[0]; d[o + 1] = c[1]; d[o + 2] = c[2]; d[o + 3] = 255;
        }
      }
      continue;
    }
    const c0 = e.planes.get(f.bands[0]), c1 = e.planes.get(f.bands[k > 1 ? 1 : 0]), c2 = e.planes.get(f.bands[k > 1 ? 2 : 0]);
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

// ---- the stretch -----------------------------------------------------------------------------
const statsCache = new Map();    // flight params + bands + percentiles -> {low, high}
const statsPending = new Set();

// [low, high] per channel of nm (the wavelengths shown), null while the statistics are coming
export function stretchRanges(nm) {
  const kind = $("stretch").value;
  const per = $("per-channel").checked && nm.length === 3;
  let pairs = null;
  if (kind === "manual") {
    const lo = Number($("stretch-low").value), hi = Number($("stretch-high").value);
    if (!(isFinite(lo) && isFinite(hi) && hi > lo) || $("stretch-low").value === "" || $("stretch-high").value === "") {
      showError("stretch: give LOW < HIGH", "err-stretch");
      return viewer.lastRanges;
    }
    clearErrors("err-stretch");
    return nm.map(() => [lo, hi]);
  }
  clearErrors("err-stretch");
  const lastRanges = viewer.lastRanges;
  if (kind === "view") {
    pairs = viewer.viewStretch && viewer.viewStretch.length === nm.length ? viewer.viewStretch : null;
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
const statsKey = (id, bands, kind) => `${id}|${statsParams(id)}|${bands}|${kind === "unscaled" ? "0,100" : "2,98"}`;

// ask for what the stretch of spec still needs (the flight's statistics), refresh when it arrives
function ensureRanges(spec) {
  const kind = $("stretch").value;
  if (kind === "view") {
    if (!viewer.viewStretch) { viewer.viewStretch = viewRanges(spec) || null; if (viewer.viewStretch) emit("refresh"); }
    return;
  }
  if (kind === "manual") return;
  const id = referenceFlight();
  if (!id) return;
  const f = viewer.byId.get(id);
  const bands = spec.nm.map((w) => nearestBand(f, w));
  const key = statsKey(id, bands, kind);
  if (statsCache.has(key) || statsPending.has(key)) return;
  statsPending.add(key);
  getJSON(`${idPath(id)}/stats?bands=${bands.join(",")}&${statsParams(id)}&percentiles=${kind === "unscaled" ? "0,100" : "2,98"}`)
    .then((st) => { statsCache.set(key, st); emit("refresh"); })
    .catch((err) => showError(err.message))
    .finally(() => statsPending.delete(key));
}

// 2 %/98 % of the values the view shows (loaded planes of the tiles in view, subsampled to at most
// VIEW_SAMPLES pixels: a stretch change stays a few milliseconds whatever the window's size)
const VIEW_SAMPLES = 40000;
export function viewRanges(spec) {
  const b = map.getBounds();
  const view = [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()];
  const k = spec.nm.length;
  const sources = [];
  let total = 0;
  for (const tile of liveTiles()) {
    const tb = tileBounds(tile.coords.z, tile.coords.x, tile.coords.y);
    if (!boxesMeet(tb, view)) continue;
    for (const f of spec.flights) {
      const planes = loadedPlanes(tile, f);
      if (!planes) continue;
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
