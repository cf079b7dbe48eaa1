// archive view: small helpers of the page: elements, numbers, JSON requests, the status line and
// the errors shown next to the control that caused them.
import { generationHeaders, viewer } from "./state.js";

export const $ = (id) => document.getElementById(id);
export const fmt = (v, digits = 4) => (v === null || v === undefined || !isFinite(v) ? "–" : Number(v).toPrecision(digits));
export const idPath = (id) => `/api/collections/${encodeURIComponent(id)}`;

export async function getJSON(url, options) {
  const response = await fetch(url, { ...(options || {}), headers: { ...generationHeaders(), ...((options || {}).headers || {}) } });
  let body = null;
  try { body = await response.json(); } catch (e) { /* not JSON */ }
  if (!response.ok) throw new Error((body && body.error) || `${response.status} ${response.statusText}`);
  return body;
}

// a refused answer as an Error (the server's message, its status as .http)
export async function refusal(response) {
  let body = null;
  try { body = await response.json(); } catch (err) { /* not JSON */ }
  return Object.assign(new Error((body && body.error) || `${response.status} ${response.statusText}`), { http: response.status });
}

export function status(text, isError = false) {
  const el = $("status");
  el.textContent = text || "";
  el.classList.toggle("error", !!isError);
}

// errors in words next to the control that caused them (the server names the parameter first)
const ERROR_SLOTS = { cubes: "err-cubes", ground_height: "err-ground", sync_offset: "err-sync", mode: "err-mode",
                      bands: "err-bands", band: "err-bands", wavelengths: "err-bands", stretch: "err-stretch",
                      bbox: "err-filters", datetime: "err-filters", wavelength: "err-filters" };
export function showError(message, slot) {
  const name = slot || ERROR_SLOTS[(message.match(/^([a-z_]+):/) || [])[1]];
  viewer.errors[name || "status"] = message;
  if (name) { $(name).textContent = message; } else status(message, true);
}
export function clearErrors(...slots) {
  for (const slot of slots.length ? slots : Object.values(ERROR_SLOTS)) { $(slot).textContent = ""; delete viewer.errors[slot]; }
  if (!slots.length) { delete viewer.errors.status; if ($("status").classList.contains("error")) status(""); }
}
