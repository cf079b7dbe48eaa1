// archive view: pinned spectra of the open flight (the pixel of archive render's grid at the
// flight's nominal GSD holding a click, float32 as render writes it), their chart (uPlot), CSV and PNG.
import { channelsNm, flightParams } from "./params.js";
import uPlot from "./vendor/uplot/uPlot.esm.js";
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
  // the chart in sight (at 1400 x 900 it lies below the panel's fold): the panel scrolls, not the page;
  // at the next frame, when uPlot has sized its canvas (it lays out in a microtask)
  requestAnimationFrame(() => $("spectrum").scrollIntoView({ block: "nearest" }));
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

// ---- the chart: uPlot (vendor/uplot/, see vendor/README.md) --------------------------------------
// One curve per pin in its colour (a missing value breaks the curve), x in nm (or band numbers when
// the flight has no wavelengths), y in the mode's unit. The bands the map shows are dashed lines
// (DOM elements over the plot, class band-mark) and the y-axis label is a DOM element (class y-label)
// shrunk, then shortened, to fit the plot's height, the whole of it as a tooltip. uPlot's legend
// reads the values under the cursor; drag to zoom in on a wavelength range, double-click to reset.
const FONT_PX = 10;
const FAMILY = `system-ui, -apple-system, "Segoe UI", Roboto, Arial, sans-serif`;
const LABEL_ROOM = 16;   // the chart's left margin (CSS px) that holds the y-axis label
let chart = null;        // the uPlot of the pins (null without pins); the tests read it as viewer.chart

// the chart's box: index.html's <div id="spectrum">
const chartBox = () => $("spectrum");
const boxSize = (box) => { const width = Math.max(200, Math.floor(box.clientWidth || 330)); return { width, height: Math.round(width * 0.64) }; };
new ResizeObserver(() => {
  if (!chart) return;
  const size = boxSize(chartBox());
  if (size.width !== chart.width) chart.setSize(size);
}).observe(chartBox());

const tickText = (t) => (Math.abs(t) >= 1e4 ? t.toExponential(1) : String(Number(t.toPrecision(12))));
const valueText = (v) => (v === null || v === undefined ? "–" : Number(v.toPrecision(6)).toString());

// the axis as wide as its longest tick label (uPlot's documented recipe)
function axisSize(u, values, i, cycle) {
  const axis = u.axes[i];
  if (cycle > 1) return axis._size;
  let size = axis.ticks.size + axis.gap;
  const longest = (values || []).reduce((a, v) => (v.length > a.length ? v : a), "");
  if (longest) { u.ctx.font = axis.font[0]; size += u.ctx.measureText(longest).width / devicePixelRatio; }
  return Math.ceil(size);
}

// the display's bands: [nm, colour, letter]
function bandMarks() {
  const nm = channelsNm().filter((w) => Number.isFinite(w));
  const marks = nm.length === 1 ? [["#666", "grey"]] : nm.length === 2 ? [["#c0392b", "a"], ["#2155c0", "b"]]
    : [["#c0392b", "R"], ["#1e8449", "G"], ["#2155c0", "B"]];
  return nm.map((w, i) => [w, ...marks[i]]);
}
const shownMarks = (u) => (u.withWavelength ? bandMarks() : []).filter(([w]) => w >= u.scales.x.min && w <= u.scales.x.max);

// after each redraw (pins, zoom, resize): the band marks over the plot, the y-axis label beside it
function placeOverlays(u) {
  u.over.querySelector(".band-marks").replaceChildren(...shownMarks(u).map(([w, colour, letter]) => {
    const mark = document.createElement("div");
    mark.className = "band-mark";
    mark.style.left = `${u.valToPos(w, "x")}px`;
    mark.style.borderLeftColor = colour;
    mark.dataset.nm = String(w);
    const text = document.createElement("span");
    text.textContent = letter; text.style.color = colour;
    mark.append(text);
    return mark;
  }));
  const label = u.root.querySelector(".y-label"), ratio = u.ctx.canvas.width / u.width;
  label.style.top = `${u.bbox.top / ratio}px`;
  label.style.height = `${u.bbox.height / ratio}px`;
  label.style.fontSize = `${FONT_PX}px`;
  label.textContent = u.yLabel;
  for (let size = FONT_PX; size > 7 && label.scrollHeight > label.clientHeight + 0.5; size -= 1) label.style.fontSize = `${size - 1}px`;
  for (let n = u.yLabel.length - 1; n > 4 && label.scrollHeight > label.clientHeight + 0.5; n -= 1) label.textContent = u.yLabel.slice(0, n) + "…";
}

// uPlot's options and data for the pins, at `scale` times the sizes of the page's chart (2: the PNG)
function chartSetup(pins, size, scale = 1) {
  const pts = pins.map((s) => s.point), ref = pts[0];
  const xsOf = (p) => p.wavelength || p.values.map((_, i) => i);
  // one x for all: pins of flights with other bands are aligned (a curve spans the others' x)
  const data = uPlot.join(pts.map((p) => [xsOf(p), p.values.map((v) => (v === undefined ? null : v))]));
  const oneFlight = pts.every((p) => p.id === ref.id);
  const label = (p) => (oneFlight ? `c${p.cube + 1} l${p.line + 1} s${p.sample + 1}` : pinLabel(p));
  const font = `${FONT_PX * scale}px ${FAMILY}`;
  const axis = { font, labelFont: font, stroke: "#334", gap: 5 * scale, ticks: { stroke: "#445", width: scale, size: 4 * scale } };
  const opts = {
    ...size,
    padding: [14 * scale, 12 * scale, 0, LABEL_ROOM * scale],
    scales: {
      x: { time: false, range: (u, lo, hi) => (lo === hi ? [lo - 1, hi + 1] : [lo, hi]) },
      y: {
        range: (u, lo, hi) => {
          if (lo === null || hi === null) return [0, 1];
          if (lo === hi) { lo -= 1; hi += 1; }
          const pad = (hi - lo) * 0.05;
          return [lo - pad, hi + pad];
        },
      },
    },
    axes: [
      { ...axis, label: ref.wavelength ? "wavelength (nm)" : "band", labelSize: 16 * scale, size: 24 * scale,
        space: 50 * scale, grid: { show: false }, values: (u, splits) => splits.map(tickText) },
      { ...axis, size: axisSize, space: 30 * scale, grid: { stroke: "#e3e6eb", width: scale }, ticks: { show: false },
        values: (u, splits) => splits.map(tickText) },
    ],
    series: [
      { label: ref.wavelength ? "nm" : "band", value: (u, v) => valueText(v) },
      ...pins.map((pin) => ({ label: label(pin.point), stroke: pin.colour, width: 1.5 * scale, value: (u, v) => valueText(v),
                              points: { size: 5 * scale, width: scale } })),
    ],
  };
  return { opts, data, withWavelength: Boolean(ref.wavelength), yLabel: `${ref.mode} (${pins[0].units})` };
}

function drawSpectrum() {
  const box = chartBox();
  if (chart) { chart.destroy(); chart = null; }
  viewer.chart = null;
  box.replaceChildren();
  box.hidden = viewer.pins.length === 0;
  if (!viewer.pins.length) return;
  const { opts, data, withWavelength, yLabel } = chartSetup(viewer.pins, boxSize(box));
  opts.legend = { live: true };
  opts.hooks = { draw: [placeOverlays] };
  chart = new uPlot(opts, data, (self, init) => {
    // the overlays exist before uPlot's first draw (which calls placeOverlays)
    Object.assign(self, { withWavelength, yLabel });
    const marks = document.createElement("div");
    marks.className = "band-marks";
    self.over.append(marks);
    const yl = document.createElement("div");
    yl.className = "y-label"; yl.title = yLabel;
    self.over.parentNode.append(yl);
    box.append(self.root);
    init();
  });
  viewer.chart = chart;
}

// the chart as a PNG: the pins drawn again by uPlot at twice the chart's size (the x range shown,
// no cursor or legend) off screen, the band marks and the y-axis label drawn over its canvas
$("png").addEventListener("click", () => {
  if (!chart) return;
  const S = 2, shown = chart, { min, max } = shown.scales.x;
  const holder = document.createElement("div");
  holder.style.cssText = "position: fixed; left: -100000px; top: 0;";
  document.body.append(holder);
  const { opts, data } = chartSetup(viewer.pins, { width: shown.width * S, height: shown.height * S }, S);
  opts.scales.x.range = () => [min, max];
  opts.legend = { show: false };
  opts.cursor = { show: false };
  const u = new uPlot(opts, data, holder);
  // uPlot draws in a microtask: compose at the next frame
  requestAnimationFrame(() => {
    const src = u.ctx.canvas, ratio = src.width / u.width;
    const canvas = document.createElement("canvas");
    canvas.width = u.width; canvas.height = u.height;
    const ctx = canvas.getContext("2d");
    ctx.fillStyle = "#fff";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    ctx.drawImage(src, 0, 0, canvas.width, canvas.height);
    const top = u.bbox.top / ratio, left = u.bbox.left / ratio, height = u.bbox.height / ratio;
    ctx.textAlign = "center";
    ctx.lineWidth = S;
    ctx.font = `${9 * S}px ${FAMILY}`;
    u.withWavelength = shown.withWavelength;
    for (const [w, colour, letter] of shownMarks(u)) {
      const x = left + u.valToPos(w, "x");
      ctx.strokeStyle = colour; ctx.fillStyle = colour;
      ctx.setLineDash([3 * S, 3 * S]);
      ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
      ctx.fillText(letter, x, top - 3 * S);
    }
    const yl = shown.root.querySelector(".y-label");
    ctx.fillStyle = "#334";
    ctx.font = `${parseFloat(getComputedStyle(yl).fontSize) * S}px ${FAMILY}`;
    ctx.textBaseline = "middle";
    ctx.translate((LABEL_ROOM * S) / 2, top + height / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.fillText(yl.textContent, 0, 0);
    u.destroy();
    holder.remove();
    canvas.toBlob((blob) => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = "spectra.png";
      viewer.png = a.href;
      a.click();
    }, "image/png");
  });
});
