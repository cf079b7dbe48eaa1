// archive view: the Leaflet map (vendored Leaflet, the global L), its wheel zoom, the flights'
// footprints and their labels; the geometry of web-mercator tiles and GeoJSON footprints (lon/lat
// degrees).
import { $, geometryOf, viewer, visibleFlights } from "./state.js";

// a tile's box: [W, S, E, N] degrees
export function tileBounds(z, x, y) {
  const n = 2 ** z;
  const lon = (i) => (i / n) * 360 - 180;
  const lat = (j) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * j) / n))) * 180) / Math.PI;
  return [lon(x), lat(y + 1), lon(x + 1), lat(y)];
}
export const boxesMeet = (a, b) => a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3];

function pointInRing(x, y, ring) {
  let inside = false;
  for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
    const [xi, yi] = ring[i], [xj, yj] = ring[j];
    if ((yi > y) !== (yj > y) && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) inside = !inside;
  }
  return inside;
}
export function inGeometry(lon, lat, g) {
  const polys = g.type === "Polygon" ? [g.coordinates] : g.type === "MultiPolygon" ? g.coordinates : [];
  return polys.some((p) => pointInRing(lon, lat, p[0]) && !p.slice(1).some((h) => pointInRing(lon, lat, h)));
}
// a (Multi)Polygon's box: [W, S, E, N]
export function geometryBox(g) {
  const box = [Infinity, Infinity, -Infinity, -Infinity];
  const polys = g.type === "Polygon" ? [g.coordinates] : g.coordinates;
  for (const p of polys) for (const [x, y] of p[0]) {
    box[0] = Math.min(box[0], x); box[1] = Math.min(box[1], y); box[2] = Math.max(box[2], x); box[3] = Math.max(box[3], y);
  }
  return box;
}

// ---- the map ---------------------------------------------------------------------------------

export const map = L.map("map", { maxZoom: 24, fadeAnimation: false, attributionControl: false, worldCopyJump: false,
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

// the shown flights' outlines (as drawn now, else their catalog footprints): viewer.footprints
export function drawFootprints() {
  if (viewer.footprints) viewer.footprints.remove();
  const features = visibleFlights().map((id) => {
    const f = viewer.byId.get(id);
    return viewer.outlines[id] ? { ...f, geometry: viewer.outlines[id].geometry } : f;
  });
  const footprints = L.geoJSON({ type: "FeatureCollection", features }, {
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
  if (!viewer.footprints || !$("show-footprints").checked) return;
  labelFont.font = "10px system-ui, sans-serif";
  const size = map.getSize(), placed = [];
  const ids = visibleFlights().reverse();
  if (viewer.open && ids.includes(viewer.open)) ids.unshift(...ids.splice(ids.indexOf(viewer.open), 1));
  for (const id of ids) {
    const [w, s, e, n] = geometryBox(geometryOf(id));
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
