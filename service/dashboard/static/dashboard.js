// Draws every element with data-chart="name" from the figure of that name, which the server
// built and embedded as JSON, and marks it data-drawn="true" once plotly.js has rendered it.
// Charts are drawn as they come near the viewport: a page opens with what is on screen drawn,
// not after every chart below the fold.
document.addEventListener("DOMContentLoaded", () => {
  const figures = JSON.parse(document.getElementById("charts").textContent);
  const config = { responsive: true, displaylogo: false };
  const draw = (element) => {
    const figure = figures[element.dataset.chart];
    if (figure === undefined) return;
    Plotly.newPlot(element, figure.data, figure.layout, config).then(() => {
      element.dataset.drawn = "true";
    });
  };
  const observer = new IntersectionObserver(
    (entries) => {
      for (const entry of entries) {
        if (entry.isIntersecting) {
          observer.unobserve(entry.target);
          draw(entry.target);
        }
      }
    },
    { rootMargin: "200px" },
  );
  for (const element of document.querySelectorAll("[data-chart]")) observer.observe(element);
});
