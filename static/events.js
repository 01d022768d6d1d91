// aerialreg's browser-to-Python event channel and chart clicks (loaded by app/gui/assets.py).
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
  const chartOf = (target) => {
    const over = target.closest && target.closest(".u-over");
    const chart = over && over.closest(".uplot");
    const title = chart && chart.querySelector(".u-title");
    return title && title.textContent.startsWith("Per-frame") ? chart : null;
  };
  const legendX = (chart) => {
    const value = chart.querySelector(".u-legend .u-series:first-child .u-value");
    return value ? parseFloat(value.textContent) : NaN;
  };
  // The frame under the pointer as last shown by the legend: a data update (the app redraws
  // the chart as frames change) blanks the legend until the pointer moves again.
  let hovered = null;
  document.addEventListener(
    "mousemove",
    (e) => {
      const chart = chartOf(e.target);
      const x = chart ? legendX(chart) : NaN;
      if (chart && Number.isFinite(x)) hovered = { x: x, t: Date.now() };
    },
    true,
  );
  document.addEventListener(
    "click",
    (e) => {
      const chart = chartOf(e.target);
      if (!chart) return;
      let x = legendX(chart);
      // (The chart element itself may have been rebuilt by a data update since the hover.)
      if (!Number.isFinite(x) && hovered && Date.now() - hovered.t < 3000) x = hovered.x;
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
