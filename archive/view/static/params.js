// archive view: what the controls ask for, read from the panel and each flight's own parameters:
// the bands of a flight nearest the wavelengths shown, the request parameters of its values (mode,
// overlap rule, cube range, ground height, sync offset, navigation source, boresight), those its
// outline and statistics depend on. Imported by controls.js, tiles.js and spectra.js; imports only
// state.js (no module of the page imports another in a circle: tests/test_view_modules.py).
import { $, viewer } from "./state.js";

// the band of a flight nearest a wavelength (nm; a band index where the flight has no wavelengths)
export function nearestBand(feature, nm) {
  const wl = feature.properties.wavelength;
  if (!wl) return Math.max(0, Math.min(feature.properties.bands - 1, Math.round(nm)));
  let best = 0;
  for (let i = 1; i < wl.length; i++) if (Math.abs(wl[i] - nm) < Math.abs(wl[best] - nm)) best = i;
  return best;
}
// the wavelengths shown: [grey] or [R, G, B] (nm)
export function channelsNm() {
  if ($("display").value === "grey") return [Number($("band-grey").value)];
  if ($("display").value === "index") return [Number($("index-a").value), Number($("index-b").value)];
  return ["band-r", "band-g", "band-b"].map((id) => Number($(id).value));
}

// the request parameters of one flight's values (everything but the bands)
export function flightParams(id, preview) {
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
    if (p.nav) q.set("navigation", p.nav);
    const bs = boresightOf(p, preview);
    if (bs) q.set("boresight", bs.map(String).join(","));
  }
  return q.toString();
}

// the boresight [roll, pitch, yaw] (degrees) of a flight's parameters, a slider preview's value in place
export const ANGLES = ["roll", "pitch", "yaw"];
export function boresightOf(p, preview) {
  if (!p.bs) return null;
  return p.bs.map((v, i) => (preview && preview[ANGLES[i]] !== undefined ? preview[ANGLES[i]] : v));
}

// the parameters an outline depends on (not the mode or overlap rule)
export function outlineParams(id) {
  const q = new URLSearchParams(flightParams(id, null));
  q.delete("mode"); q.delete("overlap");
  return q.toString();
}

// the whole flight's statistics depend on the mode and cube range, not on where its pixels land:
// a ground-height or sync change keeps its stretch (and asks nothing)
export function statsParams(id) {
  const q = new URLSearchParams(flightParams(id, null));
  for (const name of ["ground_height", "sync_offset", "overlap", "navigation", "boresight"]) q.delete(name);
  return q.toString();
}

