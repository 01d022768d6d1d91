// aerialreg's pointer readout (loaded by app/gui/assets.py): under the mouse, the pixel of the
// image it is over and, on a georeferenced map, the map coordinates there, in a line at the
// bottom left of the canvas (as QGIS's status bar shows them).
//
// The app publishes the images of every view (those of hidden views are skipped) as window.aerialregPlanes = {planes: [{node,
// label, width, height, position, scale, affine?: [a, b, c, d, e, f], unit?, crs?}]}
// (app/gui/server.py); the mouse's ray from the camera is intersected with each image's plane
// in its scene node's own frame (the geometry of app/gui/scene2d.py's PlaneGeometry), with no
// round trip to the server.
(function aerialregPointer() {
  const m = window.__viserMutable;
  if (!m || !m.camera || !m.canvas) {
    setTimeout(aerialregPointer, 200);
    return;
  }
  if (window.__aerialregPointer) return;
  window.__aerialregPointer = true;
  const box = document.createElement("div");
  box.id = "aerialreg-pointer";
  box.style.cssText =
    "position:fixed;left:8px;bottom:8px;z-index:5;padding:2px 6px;border-radius:4px;" +
    "font:12px monospace;background:rgba(255,255,255,0.85);color:#222;pointer-events:none;" +
    "display:none";
  document.body.appendChild(box);
  const fmt = (v, d) => (Math.abs(v) >= 1e5 ? v.toFixed(1) : v.toFixed(d));
  window.aerialregPointerAt = (clientX, clientY) => {
    const info = window.aerialregPlanes;
    const mm = window.__viserMutable;
    const cam = mm.camera;
    const r = mm.canvas.getBoundingClientRect();
    if (!info || !info.planes || !cam) return "";
    const V = cam.position.constructor;
    cam.updateMatrixWorld();
    const ndc = new V(((clientX - r.left) / r.width) * 2 - 1, -((clientY - r.top) / r.height) * 2 + 1, 0.5);
    const far = ndc.unproject(cam);
    for (const pl of info.planes) {
      const node = mm.nodeRefFromName[pl.node];
      if (!node) continue;
      let shown = true; // the view's images only: other views' nodes are hidden
      for (let o = node; o; o = o.parent) if (!o.visible) shown = false;
      if (!shown) continue;
      node.updateMatrixWorld(true);
      // The ray in the image node's own frame, where the image lies at z = 0 centred on the
      // origin, a pixel being pl.scale wide (app/gui/scene2d.py).
      const a = node.worldToLocal(cam.position.clone());
      const b = node.worldToLocal(far.clone());
      const dz = b.z - a.z;
      if (Math.abs(dz) < 1e-12) continue;
      const t = -a.z / dz;
      if (!(t > 0)) continue;
      const lx = a.x + t * (b.x - a.x), ly = a.y + t * (b.y - a.y);
      const x = lx / pl.scale + pl.width / 2 - 0.5;
      const y = ly / pl.scale + pl.height / 2 - 0.5;
      if (x < -0.5 || y < -0.5 || x >= pl.width - 0.5 || y >= pl.height - 0.5) continue;
      let text = `${pl.label} px ${x.toFixed(1)}, ${y.toFixed(1)}`;
      if (pl.affine) {
        const [a6, b6, c6, d6, e6, f6] = pl.affine;
        const X = a6 * (x + 0.5) + b6 * (y + 0.5) + c6, Y = d6 * (x + 0.5) + e6 * (y + 0.5) + f6;
        const deg = pl.unit === "degree";
        text += ` · ${fmt(X, deg ? 6 : 2)}, ${fmt(Y, deg ? 6 : 2)}${pl.unit && !deg ? " " + pl.unit : ""}${pl.crs ? " (" + pl.crs + ")" : ""}`;
      }
      return text;
    }
    return "";
  };
  // On the document, not on one canvas element: viser may replace its canvas.
  document.addEventListener("mousemove", (e) => {
    const text = e.target === window.__viserMutable.canvas ? window.aerialregPointerAt(e.clientX, e.clientY) : "";
    box.textContent = text;
    box.style.display = text ? "block" : "none";
  }, true);
})();
