// Time stacks (archive view --stack X.zarr): one time step of a stack at a time, a slider through
// its flights (the same grid, so the same pixels), values read from the stack's Zarr by the server.
// While a stack is shown it is drawn above the archive's flights (its own pane), the flights dimmed
// or hidden under it, and a click inside its footprint answers the stack's pixel (not the flight's).
import { inGeometry, map } from "./map.js";
import { $, fmt, getJSON, viewer } from "./state.js";

const state = { stacks: [], open: null, layer: null, outline: null, clicked: null };
map.createPane("stack").style.zIndex = 350;   // above the flights' tiles (tilePane: 200), under the outlines (400)

// the flights under a shown stack: dimmed or hidden (app.css)
function showFlights() {
  const shown = !!state.open;
  document.body.classList.toggle("stack-shown", shown);
  document.body.classList.toggle("flights-dimmed", shown && $("stack-flights").value === "dimmed");
  document.body.classList.toggle("flights-hidden", shown && $("stack-flights").value === "hidden");
}

function tileUrl() {
  const s = state.open;
  return `/api/stacks/${encodeURIComponent(s.name)}/tiles/{z}/{x}/{y}.png?time=${$("stack-time").value}`;
}

function label() {
  const t = state.open.times[Number($("stack-time").value)];
  $("stack-label").textContent = `${Number($("stack-time").value) + 1} / ${state.open.times.length}: ` +
    `${t.start.slice(0, 19).replace("T", " ")} UTC, ${t.flight}`;
}

async function showPoint() {
  const s = state.open, at = state.clicked;
  if (!s || !at) return;
  const q = `lon=${at.lng}&lat=${at.lat}&time=${$("stack-time").value}`;
  let p;
  try { p = await getJSON(`/api/stacks/${encodeURIComponent(s.name)}/point?${q}`); }
  catch (e) { $("stack-point").replaceChildren(); return; }
  const rows = p.values.map((v, b) => {
    const tr = document.createElement("tr");
    const nm = s.bands[b].wavelength;
    tr.append(Object.assign(document.createElement("td"), { textContent: nm === null ? `band ${b}` : `${nm.toFixed(1)} nm` }),
              Object.assign(document.createElement("td"), { textContent: fmt(v) }));
    return tr;
  });
  $("stack-point").replaceChildren(...rows);
}

function step() {
  label();
  state.layer.setUrl(tileUrl());
  showPoint();
}

function openStack(s) {
  closeStack();
  state.open = s;
  const slider = $("stack-time");
  slider.max = String(s.times.length - 1);
  slider.value = "0";
  $("stack-controls").hidden = false;
  state.layer = L.tileLayer(tileUrl(), { maxZoom: 24, tileSize: 256, pane: "stack" }).addTo(map);
  state.outline = L.geoJSON(s.geometry, { style: { color: "#ff7f0e", weight: 1.5, fill: false } }).addTo(map);
  map.fitBounds(state.outline.getBounds());
  showFlights();
  label();
}

function closeStack() {
  if (state.layer) map.removeLayer(state.layer);
  if (state.outline) map.removeLayer(state.outline);
  Object.assign(state, { open: null, layer: null, outline: null, clicked: null });
  $("stack-controls").hidden = true;
  $("stack-point").replaceChildren();
  showFlights();
}

// the stacks the server serves, in the panel (called once at the page's start)
export async function loadStacks() {
  let found;
  try { found = await getJSON("/api/stacks"); } catch (e) { return; }
  state.stacks = found.stacks || [];
  if (!state.stacks.length) return;
  $("stacks").hidden = false;
  $("stack-list").replaceChildren(...state.stacks.map((s) => {
    const li = document.createElement("li");
    const b = Object.assign(document.createElement("button"), { type: "button",
      textContent: `${s.name}: ${s.times.length} flights` });
    b.addEventListener("click", () => openStack(s));
    li.append(b);
    return li;
  }));
}

$("stack-time").addEventListener("input", step);
$("stack-close").addEventListener("click", closeStack);
$("stack-flights").addEventListener("change", showFlights);
// whether a point (degrees) lies inside the shown stack's footprint
const covers = (lng, lat) => !!state.open && inGeometry(lng, lat, state.open.geometry);
map.on("click", (e) => { if (covers(e.latlng.lng, e.latlng.lat)) { state.clicked = e.latlng; showPoint(); } });
viewer.stacks = { state, openStack, closeStack, covers };
