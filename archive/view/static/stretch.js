// archive view: the stretch, computed here from the reference flight's statistics (asked once per
// flight, mode, cube range and bands), the view's values or the user's range.
import { refresh } from "./controls.js";
import { $, clearErrors, getJSON, idPath, showError } from "./dom.js";
import { boxesMeet, tileBounds } from "./geo.js";
import { map } from "./map.js";
import { nearestBand, statsParams } from "./params.js";
import { referenceFlight, viewer } from "./state.js";
import { liveTiles, loadedPlanes } from "./tiles.js";

const statsCache = new Map();    // flight params + bands + percentiles -> {low, high}
const statsPending = new Set();
export function clearStats() { statsCache.clear(); }

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
export function ensureRanges(spec) {
  const kind = $("stretch").value;
  if (kind === "view") {
    if (!viewer.viewStretch) { viewer.viewStretch = viewRanges(spec) || null; if (viewer.viewStretch) refresh(); }
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
    .then((st) => { statsCache.set(key, st); refresh(); })
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
