// Draws every zoomable figure of a page: a <script type="application/json" data-plot="ID"> block holds a
// figure spec (service/web/zoomable.py) drawn into the element with that id by plotly.js (served by this
// server from the plotly package).  Traces without x take the spec's shared time axis t.
(function () {
  function draw() {
    if (typeof Plotly === "undefined") { return; }
    document.querySelectorAll("script[type='application/json'][data-plot]").forEach(function (block) {
      var target = document.getElementById(block.getAttribute("data-plot"));
      if (!target) { return; }
      var spec = JSON.parse(block.textContent);
      spec.data.forEach(function (trace) { if (trace.x === undefined) { trace.x = spec.t; } });
      Plotly.newPlot(target, spec.data, spec.layout, {responsive: true, displaylogo: false,
                                                      scrollZoom: false});
      target.setAttribute("data-drawn", "1");
    });
  }
  if (document.readyState === "loading") { document.addEventListener("DOMContentLoaded", draw); } else { draw(); }
})();
