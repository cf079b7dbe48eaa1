// archive view: pinned spectra of the open flight (the pixel of archive render's grid at the
// flight's nominal GSD holding a click, float32 as render writes it), their chart, CSV and PNG.
import { channelsNm, flightParams } from "./params.js";
import { map } from "./map.js";
import { $, MAX_PINS, PALETTE, getJSON, idPath, newGeneration, status, viewer } from "./state.js";

// pin the open flight's spectrum at a clicked point (a Leaflet LatLng)
export async function pinPoint(latlng) {
  const id = viewer.open;
  const q = new URLSearchParams(flightParams(id, null));
  q.delete("overlap");
  q.set("lon", latlng.lng.toFixed(9));
  q.set("lat", latlng.lat.toFixed(9));
  const gsd = viewer.byId.get(id).properties.gsd;
  if (gsd) q.set("gsd", String(gsd));
  let p;
  newGeneration();   // a click: drawn before the tiles of views it replaces
  try { p = await getJSON(`${idPath(id)}/point?${q}`); } catch (e) { status(e.message, true); return; }
  viewer.lastPoint = p;
  if (!p.covered) { showPixel(p); return; }
  const used = new Set(viewer.pins.map((s) => s.colour));
  const colour = PALETTE.find((c) => !used.has(c)) || PALETTE[viewer.pins.length % PALETTE.length];
  if (viewer.pins.length >= MAX_PINS) removePin(viewer.pins[0]);
  const pin = { point: p, colour, units: (viewer.info.units || {})[p.mode] || p.mode,
                marker: L.circleMarker([p.pixel.lat, p.pixel.lon], { radius: 5, color: colour, weight: 2.5, fill: false }).addTo(map) };
  viewer.pins.push(pin);
  showPixel(p);
  showPins();
  // the chart in sight (at 1400 x 900 it lies below the panel's fold): the panel scrolls, not the page
  $("spectrum").scrollIntoView({ block: "nearest" });
}
function removePin(pin) {
  pin.marker.remove();
  viewer.pins = viewer.pins.filter((s) => s !== pin);
  showPins();
}
$("clear-pins").addEventListener("click", () => { for (const pin of [...viewer.pins]) removePin(pin); });

function showPixel(p) {
  $("pixel").hidden = false;
  const rows = p.covered ? [
    ["flight", p.id],
    ["cube", `${p.cube + 1} of ${viewer.info ? viewer.info.cubes.length : "?"} (${p.base})`],
    ["line, sample", `${p.line + 1}, ${p.sample + 1} (1-based; 0-based ${p.line}, ${p.sample})`],
    ["time", `${p.utc.replace("T", " ").replace("Z", "")} UTC`],
  ] : [["pixel", "no line of the flight covers it"]];
  rows.push(["centre", `${p.pixel.lat.toFixed(7)}, ${p.pixel.lon.toFixed(7)}`],
            ["EPSG:" + p.epsg, `${p.pixel.x.toFixed(3)} E, ${p.pixel.y.toFixed(3)} N (${p.gsd} m)`],
            ["mode", p.mode + (p.saturated ? " (saturated)" : "")],
            ["ground, sync", `${p.ground_height.toFixed(2)} m, ${p.sync_offset.toFixed(3)} s`],
            ["navigation", `${p.navigation}, boresight ${p.boresight_deg.map((v) => v.toFixed(2)).join(", ")}°`]);
  $("pixel-info").replaceChildren(...rows.map(([k, v]) => {
    const tr = document.createElement("tr");
    const th = document.createElement("th"); th.textContent = k;
    const td = document.createElement("td"); td.textContent = v;
    tr.append(th, td);
    return tr;
  }));
}

function pinLabel(p) { return `${p.id} c${p.cube + 1} l${p.line + 1} s${p.sample + 1}`; }

function showPins() {
  $("pixel").hidden = viewer.pins.length === 0 && !viewer.lastPoint;
  const list = $("pins");
  list.replaceChildren(...viewer.pins.map((pin) => {
    const li = document.createElement("li");
    const swatch = document.createElement("span");
    swatch.className = "swatch"; swatch.style.background = pin.colour;
    const text = document.createElement("span");
    text.textContent = `${pinLabel(pin.point)} · ${pin.point.utc.slice(11, 23)} UTC`;
    const x = document.createElement("button");
    x.type = "button"; x.textContent = "×"; x.title = "remove"; x.setAttribute("aria-label", `remove ${pinLabel(pin.point)}`);
    x.addEventListener("click", () => removePin(pin));
    li.append(swatch, text, x);
    return li;
  }));
  drawSpectrum();
  const pts = viewer.pins.map((s) => s.point);
  if (!pts.length) { viewer.csv = null; return; }
  const xs = pts[0].wavelength || pts[0].values.map((_, i) => i);
  const header = [pts[0].wavelength ? "wavelength_nm" : "band"].concat(pts.map((p) => `${p.mode} ${pinLabel(p)}`.replace(/,/g, " ")));
  const rows = xs.map((x, i) => [x].concat(pts.map((p) => (p.values[i] === null || p.values[i] === undefined ? "" : p.values[i]))));
  const csv = [header.join(",")].concat(rows.map((r) => r.join(","))).join("\n") + "\n";
  const link = $("csv");
  if (link.href.startsWith("blob:")) URL.revokeObjectURL(link.href);
  link.href = URL.createObjectURL(new Blob([csv], { type: "text/csv" }));
  link.download = pts.length === 1 ? `${pts[0].id}_cube${pts[0].cube + 1}_line${pts[0].line}_sample${pts[0].sample}.csv` : "spectra.csv";
  viewer.csv = csv;
}

function niceTicks(lo, hi, n = 5) {
  if (!(hi > lo)) { hi = lo + 1; }
  const step0 = (hi - lo) / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0);
  const ticks = [];
  for (let t = Math.ceil(lo / step) * step; t <= hi + step * 1e-9; t += step) ticks.push(Number(t.toPrecision(12)));
  return ticks;
}

function drawSpectrum() {
  const svg = $("spectrum");
  const NS = "http://www.w3.org/2000/svg";
  // room for the y-axis label and its tick labels (the viewBox follows: the chart scales to the panel)
  const W = 360, H = 230, left = 62, right = 14, top = 14, bottom = 34;
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.replaceChildren();
  const pts = viewer.pins.map((s) => s.point);
  if (!pts.length) return;
  const el = (name, attrs, text) => {
    const e = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    svg.append(e);
    return e;
  };
  el("rect", { x: 0, y: 0, width: W, height: H, fill: "#fff" });
  const xsOf = (p) => p.wavelength || p.values.map((_, i) => i);
  const allX = pts.flatMap(xsOf), finite = pts.flatMap((p) => p.values.filter((v) => v !== null));
  const x0 = Math.min(...allX), x1 = Math.max(...allX);
  let y0 = finite.length ? Math.min(...finite) : 0, y1 = finite.length ? Math.max(...finite) : 1;
  if (y1 === y0) { y0 -= 1; y1 += 1; }
  const pad = (y1 - y0) * 0.05; y0 -= pad; y1 += pad;
  const sx = (x) => left + ((x - x0) / (x1 - x0 || 1)) * (W - left - right);
  const sy = (y) => top + (1 - (y - y0) / (y1 - y0)) * (H - top - bottom);
  for (const t of niceTicks(y0, y1)) {
    el("line", { class: "grid", x1: left, x2: W - right, y1: sy(t), y2: sy(t), stroke: "#e3e6eb" });
    el("text", { x: left - 4, y: sy(t) + 3, "text-anchor": "end", "font-size": 10 }, Math.abs(t) >= 1e4 ? t.toExponential(1) : String(t));
  }
  for (const t of niceTicks(x0, x1)) {
    el("line", { class: "axis", x1: sx(t), x2: sx(t), y1: H - bottom, y2: H - bottom + 4, stroke: "#445" });
    el("text", { x: sx(t), y: H - bottom + 14, "text-anchor": "middle", "font-size": 10 }, String(t));
  }
  // the bands the map shows
  const nm = channelsNm();
  const marks = nm.length === 1 ? [["#666", "grey"]] : [["#c0392b", "R"], ["#1e8449", "G"], ["#2155c0", "B"]];
  const ref = pts[0];
  nm.forEach((w, i) => {
    const x = ref.wavelength ? w : w;
    if (x < x0 || x > x1) return;
    el("line", { class: "band-mark", x1: sx(x), x2: sx(x), y1: top, y2: H - bottom, stroke: marks[i][0], "stroke-dasharray": "3 3" });
    el("text", { x: sx(x), y: top - 2, "text-anchor": "middle", "font-size": 9, fill: marks[i][0] }, marks[i][1]);
  });
  el("path", { class: "axis", d: `M${left},${top}V${H - bottom}H${W - right}`, stroke: "#445", fill: "none" });
  el("text", { x: (left + W - right) / 2, y: H - 4, "text-anchor": "middle", "font-size": 10 }, ref.wavelength ? "wavelength (nm)" : "band");
  const units = viewer.pins[0].units;
  // the y-axis label fits the plot's height: smaller type, then shortened (the whole of it as a tooltip)
  const label = `${ref.mode} (${units})`, room = H - top - bottom - 4;
  const yl = el("text", { class: "y-label", x: 10, y: (top + H - bottom) / 2, "text-anchor": "middle", "font-size": 10,
                          transform: `rotate(-90 10 ${(top + H - bottom) / 2})` }, label);
  for (let size = 10; size > 7 && yl.getComputedTextLength() > room; size -= 1) yl.setAttribute("font-size", size - 1);
  for (let n = label.length - 1; n > 4 && yl.getComputedTextLength() > room; n -= 1) yl.textContent = label.slice(0, n) + "…";
  const tip = document.createElementNS(NS, "title");
  tip.textContent = label;
  yl.append(tip);
  for (const pin of viewer.pins) {
    const p = pin.point, xs = xsOf(p);
    let run = [];
    const flush = () => { if (run.length) el("polyline", { class: "line", points: run.join(" "), stroke: pin.colour, "stroke-width": 1.5, fill: "none" }); run = []; };
    p.values.forEach((v, i) => { if (v === null) flush(); else run.push(`${sx(xs[i]).toFixed(2)},${sy(v).toFixed(2)}`); });
    flush();
  }
}

$("png").addEventListener("click", () => {
  const svg = $("spectrum");
  const text = new XMLSerializer().serializeToString(svg);
  const img = new Image();
  img.onload = () => {
    const canvas = document.createElement("canvas");
    canvas.width = 720; canvas.height = 460;
    const ctx = canvas.getContext("2d");
    ctx.drawImage(img, 0, 0, 720, 460);
    canvas.toBlob((blob) => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = "spectra.png";
      viewer.png = a.href;
      a.click();
    }, "image/png");
  };
  img.src = "data:image/svg+xml;charset=utf-8," + encodeURIComponent(text);
});

