// wtbench report: table sorting, column toggles and the frame viewer. No libraries, no network.
"use strict";

function cellValue(row, col, numeric) {
  const cell = row.cells[col];
  if (!cell) return null;
  const raw = cell.hasAttribute("data-v") ? cell.getAttribute("data-v") : cell.textContent.trim();
  if (raw === "") return null;
  return numeric ? parseFloat(raw) : raw.toLowerCase();
}

// Sort a table's body by one column: best first on the first click, reversed on the next; empty cells last.
function sortTable(table, th) {
  const col = parseInt(th.dataset.col, 10);
  const numeric = th.dataset.type === "num";
  const best = th.dataset.best === "desc" ? "descending" : "ascending";
  const current = th.getAttribute("aria-sort");
  const order = current === best ? (best === "ascending" ? "descending" : "ascending") : best;
  const sign = order === "ascending" ? 1 : -1;
  const body = table.tBodies[0];
  const rows = Array.from(body.rows);
  rows.sort((a, b) => {
    const x = cellValue(a, col, numeric), y = cellValue(b, col, numeric);
    if (x === null || (numeric && isNaN(x))) return (y === null || (numeric && isNaN(y))) ? 0 : 1;
    if (y === null || (numeric && isNaN(y))) return -1;
    if (x < y) return -sign;
    if (x > y) return sign;
    return 0;
  });
  rows.forEach((r) => body.appendChild(r));
  table.querySelectorAll("th[aria-sort]").forEach((h) => h.removeAttribute("aria-sort"));
  th.setAttribute("aria-sort", order);
}

document.querySelectorAll("table.sortable").forEach((table) => {
  table.querySelectorAll("thead th[data-col]").forEach((th) => {
    th.addEventListener("click", () => sortTable(table, th));
  });
});

document.querySelectorAll(".toggles").forEach((box) => {
  const table = document.getElementById(box.dataset.table);
  box.querySelectorAll("input[type=checkbox]").forEach((cb) => {
    cb.addEventListener("change", () => table.classList.toggle("hide-" + cb.dataset.metric, !cb.checked));
  });
});

document.querySelectorAll(".viewer").forEach((viewer) => {
  const frames = viewer.querySelectorAll(".frame");
  const range = viewer.querySelector(".frame-range");
  const name = viewer.querySelector(".frame-name");
  function show(i) {
    frames.forEach((f, k) => { f.hidden = k !== i; });
    name.textContent = frames[i].dataset.name;
    range.value = String(i);
  }
  range.addEventListener("input", () => show(parseInt(range.value, 10)));
  document.addEventListener("keydown", (ev) => {
    if (ev.target instanceof HTMLInputElement) return; // a focused slider moves by itself
    const i = parseInt(range.value, 10);
    if (ev.key === "ArrowRight" && i < frames.length - 1) show(i + 1);
    if (ev.key === "ArrowLeft" && i > 0) show(i - 1);
  });
});
