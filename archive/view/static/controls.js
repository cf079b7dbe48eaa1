// archive view: the panel's controls (catalog list and filters, overlap rule, display, the open
// flight's cubes, ground, sync and boresight sliders, its navigation source; what they ask for is
// params.js's), the overlap rule chosen (one of those the server offers), refresh():
// every change makes a new spec of what the tiles show (tiles.js draws it), and the URL hash: the
// state of the page, shareable; editing it updates the view.
import { drawFootprints, geometryBox, inGeometry, map } from "./map.js";
import { ANGLES, boresightOf, channelsNm, flightParams, nearestBand, outlineParams } from "./params.js";
import { pinPoint } from "./spectra.js";
import { $, PREVIEW_UP, clearErrors, fmt, geometryOf, getJSON, idPath, newGeneration, on, referenceFlight, showError, status,
         viewer, visibleFlights } from "./state.js";
import { markPlaceholders, pump, schedule, stretchRanges, viewRanges } from "./tiles.js";

// the band selects of the three displays (RGB, grey, index a and b), filled from the reference flight
const BAND_SELECTS = ["band-r", "band-g", "band-b", "band-grey", "index-a", "index-b"];

// the overlap rule chosen ({name, label, key, wins} as /api/collections serves it); before the list
// has arrived, a rule that picks the later flight and needs no key
function overlapRule() {
  const name = $("overlap").value;
  return viewer.overlaps.find((r) => r.name === name) || viewer.overlaps[0] || { name, key: null, wins: "last" };
}

// a flight's box (lon/lat), padded: by half its size while its footprint may have moved (a new
// ground height, sync offset, navigation source, boresight or cube range whose outline has not arrived, a slider preview), else
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


// ---- the spec: what every tile should show (tiles.js) -----------------------------------------
function buildSpec() {
  const nm = channelsNm();
  const preview = viewer.preview;
  const flights = visibleFlights().map((id) => {
    const f = viewer.byId.get(id);
    const coarse = preview && id === viewer.open;
    return { id, params: flightParams(id, coarse ? preview : null), bands: nm.map((w) => nearestBand(f, w)),
             up: coarse ? PREVIEW_UP : 0, box: flightBox(id, coarse) };
  });
  const index = $("display").value === "index";
  const ranges = index ? [[-1, 1]] : stretchRanges(nm);   // an index is drawn on its fixed ramp
  // the overlap rule says what it needs (a per-pixel key plane) and which capture a pixel shows
  const rule = overlapRule();
  const keyed = !!rule.key, lowest = keyed && rule.wins === "lowest";
  const data = JSON.stringify(flights.map((f) => [f.id, f.params, f.bands, f.up]));
  return { flights, nm, ranges, keyed, lowest, data, id: data + JSON.stringify(ranges) + keyed, grey: nm.length === 1, index };
}

export function refresh() {
  // before the first view is set (the hash's, else the fit of every footprint) nothing is asked for:
  // the world view's tiles would be thrown away at once
  if (!viewer.booted) return;
  const spec = buildSpec();
  if (spec.ranges) viewer.lastRanges = spec.ranges;   // else new statistics are coming: draw when they arrive
  if (!viewer.current || spec.id !== viewer.current.id) { viewer.failedSpec = null; newGeneration(); }
  viewer.current = spec;
  markPlaceholders(spec);
  viewer.ready = viewer.settled = false;
  showOutputs();
  writeHash();
  pump();
}

// ---- the catalog: every flight matching the filters, on the map and in the list ---------------
export async function loadCatalog(fit) {
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
  if (fc.overlaps) setOverlaps(fc.overlaps);
  viewer.features = fc.features;
  viewer.byId = new Map(fc.features.map((f) => [f.id, f]));
  const known = viewer.order.filter((id) => viewer.byId.has(id));
  viewer.order = known.concat(fc.features.map((f) => f.id).filter((id) => !known.includes(id)));
  if (viewer.open && !viewer.byId.has(viewer.open)) closeFlight();
  fillBandOptions();
  drawFootprints();
  renderList();
  status(`${fc.features.length} flight(s)`);
  if (fit && fc.features.length && !viewer.hashHasMap) fitFlights();
  refresh();
}

// the view of every flight listed: the zoom that fits them all, or, where that is finer than the
// overview previews the flights were ingested with serve (properties.previews_zoom: their finest
// zoom) by at most PREVIEWS_ZOOM_OUT levels and no flight is open, that zoom: the first screen then
// comes from the previews, without the DN (issue 49 item 7). An open flight is drawn from its DN
// whatever the zoom (its own parameters), and further out the flights would be too small to see.
const PREVIEWS_ZOOM_OUT = 2;
export function fitFlights() {
  map.fitBounds(viewer.footprints.getBounds(), { padding: [20, 20], animate: false });
  const zooms = viewer.features.filter((f) => !viewer.hidden.has(f.id)).map((f) => f.properties.previews_zoom)
    .filter((z) => Number.isInteger(z));
  const served = zooms.length ? Math.min(...zooms) : null;
  if (!viewer.open && served !== null && map.getZoom() > served && map.getZoom() - served <= PREVIEWS_ZOOM_OUT) {
    map.setZoom(served, { animate: false });
  }
}

// the overlap rules the server offers ({name, label, key, wins}, the first the default) in the list
function setOverlaps(rules) {
  viewer.overlaps = rules;
  const select = $("overlap");
  const keep = select.value;
  select.replaceChildren(...rules.map((r) => Object.assign(document.createElement("option"), { value: r.name, textContent: r.label })));
  select.value = rules.some((r) => r.name === keep) ? keep : rules[0].name;
}
const defaultOverlap = () => (viewer.overlaps[0] || { name: "" }).name;

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
  const keep = BAND_SELECTS.map((s) => $(s).value);
  for (const sel of BAND_SELECTS) {
    const select = $(sel);
    select.replaceChildren();
    for (let i = 0; i < p.bands; i++) {
      const o = document.createElement("option");
      o.value = p.wavelength ? String(p.wavelength[i]) : String(i);
      o.textContent = p.wavelength ? `${i + 1}: ${p.wavelength[i].toFixed(1)} nm` : `band ${i + 1}`;
      select.append(o);
    }
  }
  if (keep[0] === "") { setTrueColour(false); setNdvi(false); }
  else BAND_SELECTS.forEach((s, i) => selectNearest($(s), Number(keep[i])));
  if (!$("mode").options.length) setModes(["raw", "relative", "radiance"], "radiance");
}
// NDVI's bands as archive stats maps them (the Awesome Spectral Indices catalogue's N and R, the
// centres of their ranges): a nearest 830 nm, b nearest 654 nm
function setNdvi(apply = true) {
  selectNearest($("index-a"), 830);
  selectNearest($("index-b"), 654);
  if (apply) { $("display").value = "index"; showDisplay(); refresh(); }
}
$("ndvi").addEventListener("click", () => setNdvi());
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
export function showDisplay() {
  const kind = $("display").value, grey = kind === "grey", index = kind === "index";
  for (const el of document.querySelectorAll(".row.rgb")) el.hidden = kind !== "rgb";
  for (const el of document.querySelectorAll(".row.grey")) el.hidden = !grey;
  for (const el of document.querySelectorAll(".row.index")) el.hidden = !index;
  document.querySelector(".row.stretch").hidden = index;   // an index has its fixed ramp
  $("per-channel-label").hidden = grey;
  document.querySelector(".row.manual").hidden = index || $("stretch").value !== "manual";
}

for (const id of BAND_SELECTS) $(id).addEventListener("change", () => refresh());
$("display").addEventListener("change", () => { showDisplay(); refresh(); });
$("mode").addEventListener("change", () => refresh());
$("truecolour").addEventListener("click", () => setTrueColour(true));
$("stretch").addEventListener("change", () => {
  if ($("stretch").value === "view") viewer.viewStretch = viewer.current ? viewRanges(viewer.current) : null;
  const lastRanges = viewer.lastRanges;
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
  if ($("stretch").value === "view" && viewer.current) { viewer.current.viewStretchFresh = false; }
  writeHash();
  schedule();
});

function showOutputs() {
  const preview = viewer.preview;
  if (viewer.open && viewer.params[viewer.open]) {
    const p = viewer.params[viewer.open];
    const g = preview && preview.ground !== undefined ? preview.ground : p.ground;
    const s = preview && preview.sync !== undefined ? preview.sync : p.sync;
    $("ground-out").textContent = `${Number(g).toFixed(1)} m`;
    $("sync-out").textContent = `${Number(s).toFixed(3)} s`;
    (boresightOf(p, preview) || []).forEach((v, i) => showOutputsValue(ANGLES[i], v));
  }
  const r = viewer.current && viewer.current.ranges;
  const names = { grey: ["grey"], index: ["index"] }[$("display").value] || ["R", "G", "B"];
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
  if (!viewer.params[id]) viewer.params[id] = asIngested(info);
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

// a flight's own parameters as ingested (the navigation source: the one drawn by default)
function asIngested(info) {
  return { cubes: null, ground: info.ground_height, sync: info.sync_offset, nav: info.navigation.default,
           bs: info.boresight_deg.slice() };
}
const sameAngles = (a, b) => a.every((v, i) => Math.abs(v - b[i]) < 1e-9);

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
  const nav = $("navigation");
  nav.replaceChildren(...info.navigation.sources.map((name) => Object.assign(document.createElement("option"), {
    value: name, textContent: name === "lcf" ? "lcf (real-time)" : name })));
  nav.value = p.nav;
  nav.disabled = info.navigation.sources.length < 2;
  ANGLES.forEach((name, i) => {
    const el = $(`bs-${name}`);
    el.min = (info.boresight_deg[i] - 2).toFixed(2); el.max = (info.boresight_deg[i] + 2).toFixed(2);
    el.value = p.bs[i];
  });
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
let previewFrame = null;
export function startPreview(value) {
  viewer.previewNext = null;
  viewer.preview = value;
  refresh();
}
// what tiles.js asks for (it imports nothing of this module): a new spec, the waiting slider preview
on("refresh", () => refresh());
on("preview", (value) => startPreview(value));
for (const [id, name] of [["ground", "ground"], ["sync", "sync"], ["bs-roll", "roll"], ["bs-pitch", "pitch"], ["bs-yaw", "yaw"]]) {
  $(id).addEventListener("input", () => {
    viewer.previewNext = { [name]: Number($(id).value) };
    showOutputsValue(name, viewer.previewNext[name]);
    if ((viewer.preview && !viewer.settled) || previewFrame !== null) return;   // the settled preview starts the next
    previewFrame = requestAnimationFrame(() => {
      previewFrame = null;
      if (viewer.previewNext !== null) startPreview(viewer.previewNext);
    });
  });
  $(id).addEventListener("change", () => {
    viewer.preview = null; viewer.previewNext = null;
    const p = viewer.params[viewer.open];
    if (ANGLES.includes(name)) p.bs[ANGLES.indexOf(name)] = Number($(id).value);
    else p[name] = Number($(id).value);
    flightChanged();
  });
}
function showOutputsValue(name, v) {
  if (name === "ground") $("ground-out").textContent = `${v.toFixed(1)} m`;
  else if (name === "sync") $("sync-out").textContent = `${v.toFixed(3)} s`;
  else $(`bs-${name}-out`).textContent = `${v.toFixed(2)}°`;
}
// the navigation source: a change redraws like a band change (the old picture stays until the new one is in)
$("navigation").addEventListener("change", () => {
  viewer.params[viewer.open].nav = $("navigation").value;
  flightChanged();
});

$("reset").addEventListener("click", () => {
  const info = viewer.info;
  viewer.params[info.id] = asIngested(info);
  setSliders(info);
  setModes(info.modes, info.default_mode);
  $("mode").value = info.default_mode;
  $("stretch").value = "flight";
  $("per-channel").checked = true;
  setTrueColour(false);
  $("display").value = "rgb";
  showDisplay();
  clearErrors();
  viewer.failedSpec = null;
  flightChanged();
});
$("close").addEventListener("click", () => { closeFlight(); status(""); });

// ---- clicks: open the flight under the pointer, or pin the open flight's spectrum -------------
map.on("click", (ev) => {
  const { lng, lat } = ev.latlng;
  if (viewer.stacks && viewer.stacks.covers(lng, lat)) return;   // a stack pixel: the stack's value (stacks.js)
  const under = visibleFlights().filter((id) => inGeometry(lng, lat, geometryOf(id)));
  if (viewer.open && (under.includes(viewer.open) || !under.length)) { pinPoint(ev.latlng); return; }
  if (under.length) openFlight(under[under.length - 1], false);
});

// ---- the URL hash: the state of the page, shareable; editing it updates the view --------------
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
      if (p.nav !== viewer.info.navigation.default) s.set("nav", p.nav);
      if (p.bs && !sameAngles(p.bs, viewer.info.boresight_deg)) s.set("boresight", p.bs.map(String).join(","));
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
function writeHash() {
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
  if (bands.length === 2) { $("display").value = "index"; selectNearest($("index-a"), bands[0]); selectNearest($("index-b"), bands[1]); }
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
    if (s.has("nav") && viewer.info.navigation.sources.includes(s.get("nav"))) p.nav = s.get("nav");
    else if (!initial) p.nav = viewer.info.navigation.default;
    const bs = (s.get("boresight") || "").split(",").map(Number);
    if (bs.length === 3 && bs.every(isFinite)) p.bs = bs;
    else if (!initial) p.bs = viewer.info.boresight_deg.slice();
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
