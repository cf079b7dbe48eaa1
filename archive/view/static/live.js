// archive watch: the live map. Served by 'archive watch' (GET /api/live); under 'archive view' that
// answers 404 and this module does nothing. Every POLL_MS it asks /api/live; when a cube has been
// listed (or a flight's collection has replaced its cubes) it reloads the catalog, so that the new
// cube's footprint and band-value tiles are drawn at once (a listed cube is a raw flight of its own,
// never changed: nothing cached goes stale). Over the imagery it draws each pass's coverage outline
// and, filled, the gaps between passes (ground nobody imaged: the pilot can fly it again before
// leaving), and a line per flight (cubes, lines, what the watcher is doing). The last answer is
// viewer.live (the browser tests read it); viewer.liveLoads counts the catalog reloads it made.
import { loadCatalog } from "./controls.js";
import { map } from "./map.js";
import { viewer } from "./state.js";

const POLL_MS = 500;
const PASS_STYLE = { color: "#00e676", weight: 2, fill: false, dashArray: "4 3", interactive: false };
const GAP_STYLE = { color: "#ff1744", weight: 1, fill: true, fillColor: "#ff1744", fillOpacity: 0.35, interactive: false };

viewer.live = null;
viewer.liveLoads = 0;
let seen = null, layer = null, panel = null;

function draw(answer) {
  if (layer) layer.remove();
  layer = L.layerGroup();
  for (const f of answer.flights) {
    for (const pass of f.passes || []) if (pass.coordinates.length) layer.addLayer(L.geoJSON(pass, { pane: "live", style: () => PASS_STYLE }));
    if (f.gaps && f.gaps.coordinates.length) layer.addLayer(L.geoJSON(f.gaps, { pane: "live", style: () => GAP_STYLE }));
  }
  layer.addTo(map);
  panel.getContainer().replaceChildren(...answer.flights.map((f) => {
    const row = document.createElement("div");
    const gaps = f.gaps && f.gaps.coordinates.length ? ` · ${f.gaps.coordinates.length} gap(s)` : "";
    const skipped = f.skipped && f.skipped.length ? ` · skipped ${f.skipped.join(", ")}` : "";
    row.textContent = `${f.id}: ${f.cubes} cube(s), ${f.lines} lines, ${(f.passes || []).length} pass(es)${gaps} · ` +
      `${f.complete ? "complete: " + f.collection : f.status}${skipped}`;
    row.dataset.flight = f.id;
    return row;
  }));
}

async function poll() {
  if (!viewer.booted) { setTimeout(poll, 100); return; }
  let answer = null;
  try {
    const response = await fetch("/api/live", { cache: "no-store" });
    if (response.status === 404) return;   // not a watch: no live flights, ever
    if (response.ok) answer = await response.json();
  } catch (e) { /* the watcher restarts: ask again */ }
  if (answer) {
    if (!panel) start();
    viewer.live = answer;
    const key = JSON.stringify(answer.flights.map((f) => [f.id, f.cube_ids, f.collection, f.complete, f.status]));
    if (key !== seen) {
      const first = !viewer.features.length;
      seen = key;
      draw(answer);
      viewer.liveLoads += 1;
      await loadCatalog(first);   // fit the map to the first cubes listed
    }
  }
  setTimeout(poll, POLL_MS);
}

function start() {
  map.createPane("live").style.zIndex = 450;   // over the imagery (tilePane: 200)
  map.getPane("live").style.pointerEvents = "none";
  const Panel = L.Control.extend({ onAdd: () => Object.assign(L.DomUtil.create("div", "live-panel"), {
    style: "background: rgba(255,255,255,0.85); padding: 2px 6px; font: 11px system-ui, sans-serif; max-width: 28em" }) });
  panel = new Panel({ position: "bottomright" }).addTo(map);
}

poll();
