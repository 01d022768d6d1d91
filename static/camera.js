// Pan-only camera for 2D images in viser's 3D scene (notes/viser.md section 2).
// Left- and right-drag pan (camera-controls ACTION.TRUCK = 2) instead of orbiting, one-finger
// touch pans (TOUCH_TRUCK = 128), the wheel zooms towards the cursor. Uses the viser client's
// private window.__viserMutable.cameraControl; if a viser upgrade removes it, orbiting simply
// comes back. Retries until the client has built its camera controls.
(function panOnlyCamera() {
  const m = window.__viserMutable;
  if (!m || !m.cameraControl) {
    setTimeout(panOnlyCamera, 100);
    return;
  }
  const c = m.cameraControl;
  c.mouseButtons.left = 2;
  c.mouseButtons.right = 2;
  c.touches.one = 128;
  c.dollyToCursor = true;
})();
