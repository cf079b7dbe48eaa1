// archive view: every flight of the catalog on one map, drawn from band-value tiles that this page
// stretches and composes itself. The page's script is ES modules (no build step; the vendored
// Leaflet is the one classic script, the global L): state.js (the one state object, also
// window.viewer, which the browser tests read; the small helpers), map.js (the map, footprints,
// tile geometry), tiles.js (band-value tiles, their drawing, the stretch), controls.js (the panel,
// refresh, the URL hash), spectra.js, stacks.js, zones.js; residual.js is loaded beside. This one starts the page.
import { applyHash, fitFlights, loadCatalog, refresh, showDisplay } from "./controls.js";
import { map } from "./map.js";
import { loadStacks } from "./stacks.js";
import { $, viewer } from "./state.js";
import { loadZones } from "./zones.js";
import "./live.js";   // archive watch: the live flights (does nothing under archive view)

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
  viewer.hashHasMap = false;
  const catalog = loadCatalog(false);
  loadStacks();
  loadZones();
  await catalog;
  const s = new URLSearchParams(location.hash.slice(1));
  if (location.hash.length > 1) await applyHash(true);
  if (!s.has("map") && viewer.footprints && viewer.features.length) fitFlights();
  showDisplay();
  viewer.booted = true;
  refresh();
})();
