// archive view: the URL hash, the state of the page, shareable; editing it updates the view.
import { closeFlight, defaultOverlap, loadOutline, openFlight, refresh, renderList, selectNearest, setSliders,
         showDisplay } from "./controls.js";
import { $ } from "./dom.js";
import { drawFootprints, map } from "./map.js";
import { channelsNm } from "./params.js";
import { viewer, visibleFlights } from "./state.js";

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
  if ($("overlap").value !== defaultOverlap()) s.set("overlap", $("overlap").value);
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
export function writeHash() {
  if (!viewer.booted) return;
  clearTimeout(hashTimer);
  hashTimer = setTimeout(() => {
    const h = "#" + hashState();
    if (location.hash !== h) { writing = true; history.replaceState(null, "", h); writing = false; }
    viewer.hash = h;
  }, 100);
}

export async function applyHash(initial) {
  const s = new URLSearchParams(location.hash.slice(1));
  const m = (s.get("map") || "").split("/").map(Number);
  if (m.length === 3 && m.every(isFinite)) { map.setView([m[1], m[2]], m[0], { animate: false }); viewer.hashHasMap = true; }
  if (s.has("flights")) {
    const shown = s.get("flights").split(",").filter(Boolean);
    const all = viewer.features.map((f) => f.id);
    viewer.hidden = new Set(all.filter((id) => !shown.includes(id)));
    viewer.order = all.filter((id) => !shown.includes(id)).concat(shown.filter((id) => all.includes(id)));
  } else if (!initial) { viewer.hidden = new Set(); }
  $("overlap").value = s.has("overlap") ? s.get("overlap") : defaultOverlap();
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
