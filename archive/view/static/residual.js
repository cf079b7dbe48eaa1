// Residual misregistration between two time steps of a stack (issue 33): a small map control picks
// a stack and two of its flights; /api/stacks/{name}/residual measures the shift of every textured
// window from the first to the second, drawn as dots coloured by its length (green <= 0.2 px,
// amber <= 0.5 px, red beyond) with its shift in the tooltip, and the median / p95 below.
// A module (index.html loads it after app.js): map, getJSON and the page's state imported.
import { map } from "./map.js";
import { getJSON, viewer } from "./state.js";

(function () {
  const state = { stacks: [], layer: null };
  const control = L.control({ position: "bottomleft" });

  function el(tag, props, ...children) {
    const e = Object.assign(document.createElement(tag), props || {});
    e.append(...children);
    return e;
  }

  function colour(px) {
    return px <= 0.2 ? "#1a9850" : px <= 0.5 ? "#fdae61" : "#d73027";
  }

  function fillTimes() {
    const s = state.stacks.find((v) => v.name === control.stack.value);
    for (const [sel, k] of [[control.a, 0], [control.b, 1]]) {
      sel.replaceChildren(...(s ? s.times : []).map((t) =>
        el("option", { value: String(t.index), textContent: `${t.index + 1}: ${t.flight}` })));
      if (s && s.times.length > k) sel.value = String(k);
    }
  }

  async function show() {
    const name = control.stack.value;
    if (!name) return;
    control.out.textContent = "measuring...";
    const q = `a=${control.a.value}&b=${control.b.value}`;
    let r;
    try {
      r = await getJSON(`/api/stacks/${encodeURIComponent(name)}/residual?${q}`);
    } catch (e) {
      control.out.textContent = String(e.message || e);
      return;
    }
    if (state.layer) state.layer.remove();
    state.layer = L.layerGroup(r.windows.map((w) => L.circleMarker([w.lat, w.lon], {
      radius: 5, weight: 1, color: "#222", fillColor: colour(w.px), fillOpacity: 0.9,
    }).bindTooltip(`${w.px.toFixed(2)} px (E ${w.east_px.toFixed(2)}, N ${w.north_px.toFixed(2)})`))).addTo(map);
    control.out.textContent = r.matched
      ? `median ${r.median.toFixed(2)} px, p95 ${r.p95.toFixed(2)} px of ${r.gsd} m (${r.matched} of ${r.textured} textured windows)`
      : `no window matched (${r.textured} textured)`;
    viewer.residual = r;   // the browser tests read it
  }

  control.onAdd = function () {
    const div = el("div", { className: "leaflet-bar residual-control", id: "residual" });
    div.style.background = "white";
    div.style.padding = "4px";
    this.stack = el("select", { id: "residual-stack", title: "stack" });
    this.a = el("select", { id: "residual-a", title: "first flight" });
    this.b = el("select", { id: "residual-b", title: "second flight" });
    const go = el("button", { type: "button", id: "residual-show", textContent: "misregistration" });
    const hide = el("button", { type: "button", textContent: "×", title: "hide" });
    this.out = el("div", { id: "residual-out", className: "small" });
    this.stack.addEventListener("change", fillTimes);
    go.addEventListener("click", show);
    hide.addEventListener("click", () => { if (state.layer) state.layer.remove(); state.layer = null; });
    div.append(el("div", {}, this.stack, " ", this.a, " vs ", this.b, " ", go, hide), this.out);
    L.DomEvent.disableClickPropagation(div);
    return div;
  };

  getJSON("/api/stacks").then((r) => {
    state.stacks = r.stacks || [];
    if (!state.stacks.length) return;      // nothing to compare: no control
    control.addTo(map);
    control.stack.replaceChildren(...state.stacks.map((s) => el("option", { value: s.name, textContent: s.name })));
    fillTimes();
  }).catch(() => {});
})();
