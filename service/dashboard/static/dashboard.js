// Draws every element with data-chart="name" from the figure of that name, which the server
// built and embedded as JSON; marks it data-drawn="true" once plotly.js has rendered it.
document.addEventListener("DOMContentLoaded", () => {
  const figures = JSON.parse(document.getElementById("charts").textContent);
  const config = { responsive: true, displaylogo: false };
  for (const element of document.querySelectorAll("[data-chart]")) {
    const figure = figures[element.dataset.chart];
    if (figure === undefined) continue;
    Plotly.newPlot(element, figure.data, figure.layout, config).then(() => {
      element.dataset.drawn = "true";
    });
  }
});
