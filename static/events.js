// aerialreg's browser-to-Python event channel and chart clicks (loaded by app/assets.py).
//
// window.aerialreg.send(kind, value) delivers {kind, value} to the app: it sets the value of a
// hidden text widget (uuid __CHANNEL__) through the viser client's private
// window.__viserMutable.sendMessage, exactly as the widget itself would; Python's on_update
// callback parses it. Rows of the app's HTML tables call it from their onclick attributes.
//
// A click on a uPlot chart whose title starts with "Per-frame" sends ("plot-frame", x), x being
// the x value the chart's legend shows for the cursor (the hovered frame), so zooming the
// chart does not break the mapping.
(function aerialregEvents() {
  const channel = "__CHANNEL__";
  let counter = 0;
  window.aerialreg = {
    send(kind, value) {
      const m = window.__viserMutable;
      if (!m || !m.sendMessage) return false;
      counter += 1;
      m.sendMessage({
        type: "GuiUpdateMessage",
        uuid: channel,
        updates: { value: JSON.stringify({ kind: kind, value: value, n: counter, t: Date.now() }) },
      });
      return true;
    },
  };
  if (window.__aerialregPlotClicks) return;
  window.__aerialregPlotClicks = true;
  document.addEventListener(
    "click",
    (e) => {
      const over = e.target.closest && e.target.closest(".u-over");
      if (!over) return;
      const chart = over.closest(".uplot");
      if (!chart) return;
      const title = chart.querySelector(".u-title");
      if (!title || !title.textContent.startsWith("Per-frame")) return;
      const value = chart.querySelector(".u-legend .u-series:first-child .u-value");
      if (!value) return;
      const x = parseFloat(value.textContent);
      if (Number.isFinite(x)) window.aerialreg.send("plot-frame", Math.round(x));
    },
    true,
  );
})();

// Tag the app's per-frame charts (by their title) so app.css can hide the marker series' values
// in the legend: their "no marker here" points are NaN (uPlot has no NaN gaps).
(function tagCharts() {
  const tag = () =>
    document.querySelectorAll(".uplot").forEach((chart) => {
      const title = chart.querySelector(".u-title");
      if (title && /^(Per-frame|Straightness)/.test(title.textContent)) {
        chart.classList.add("aerialreg-chart");
      }
    });
  new MutationObserver(tag).observe(document.body, { childList: true, subtree: true });
  tag();
})();
