"use strict";
// Small SVG helpers for the panel's plots: elements, linear and log scales, axes. No library is needed.
const SVG = (() => {
  const NS = "http://www.w3.org/2000/svg";

  function el(parent, name, attrs = {}, text = null) {
    const node = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
    if (text !== null) node.textContent = text;
    if (parent) parent.appendChild(node);
    return node;
  }

  function clear(svg) {
    while (svg.firstChild) svg.removeChild(svg.firstChild);
  }

  function linear(d0, d1, r0, r1) {
    const k = (r1 - r0) / ((d1 - d0) || 1);
    return (v) => r0 + (v - d0) * k;
  }

  // Log scale over whole decades that contain [lo, hi] (lo > 0).
  function logDomain(values, floor = 1e-3) {
    const pos = values.filter((v) => v > 0);
    const lo = Math.min(floor, ...pos), hi = Math.max(10 * floor, ...pos);
    return [Math.pow(10, Math.floor(Math.log10(lo))), Math.pow(10, Math.ceil(Math.log10(hi)))];
  }

  function log(d0, d1, r0, r1) {
    const f = linear(Math.log10(d0), Math.log10(d1), r0, r1);
    return (v) => f(Math.log10(Math.max(v, d0)));
  }

  // Horizontal grid lines and labels at each decade of a log axis.
  function logAxis(svg, d0, d1, y, x0, x1) {
    for (let e = Math.round(Math.log10(d0)); e <= Math.round(Math.log10(d1)); e++) {
      const v = Math.pow(10, e), py = y(v);
      el(svg, "line", { x1: x0, x2: x1, y1: py, y2: py, stroke: "#e3e5ea" });
      el(svg, "text", { x: x0 - 4, y: py + 4, "text-anchor": "end" }, e >= 0 ? String(v) : v.toExponential(0));
    }
  }

  function title(node, text) {
    el(node, "title", {}, text);
    return node;
  }

  return { el, clear, linear, log, logDomain, logAxis, title };
})();
