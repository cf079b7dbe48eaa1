// archive view: what the display controls ask for: the bands of each flight, the request parameters
// of its values, the overlap rule chosen (one of those the server offers), and each flight's box.
import { $ } from "./dom.js";
import { geometryBox } from "./geo.js";
import { viewer } from "./state.js";

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
  return ["band-r", "band-g", "band-b"].map((id) => Number($(id).value));
}

// the overlap rule chosen ({name, label, key, wins} as /api/collections serves it); before the list
// has arrived, a rule that picks the later flight and needs no key
export function overlapRule() {
  const name = $("overlap").value;
  return viewer.overlaps.find((r) => r.name === name) || viewer.overlaps[0] || { name, key: null, wins: "last" };
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
  }
  return q.toString();
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
  for (const name of ["ground_height", "sync_offset", "overlap"]) q.delete(name);
  return q.toString();
}

// a flight's box (lon/lat), padded: by half its size while its footprint may have moved (a new
// ground height, sync offset or cube range whose outline has not arrived, a slider preview), else
// by a tenth (the outline samples the meshes' edges): tiles outside it are not asked for
export function flightBox(id, moving) {
  const f = viewer.byId.get(id);
  const o = viewer.outlines[id];
  const known = !moving && (o ? o.params === outlineParams(id) : !viewer.params[id]);
  const b = geometryBox((o && o.geometry) || f.geometry);
  const pad = known ? 0.1 : 0.5;
  const dx = (b[2] - b[0]) * pad + 1e-4, dy = (b[3] - b[1]) * pad + 1e-4;
  return [b[0] - dx, b[1] - dy, b[2] + dx, b[3] + dy];
}
