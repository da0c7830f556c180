// The loaded models (GET /v1/models): each manifest's version, task, evaluation figures and MLflow run.
import { el, fmt } from "./dom.js";

const HEADLINE_METRICS = 3;

export async function loadModels(key) {
  const r = await fetch("/v1/models", { headers: key ? { "X-API-Key": key } : {} });
  if (r.status === 401) throw new Error("this service asks for its API key: enter it above");
  if (!r.ok) throw new Error(`/v1/models answered ${r.status}`);
  return r.json();
}

// The registered model's page: its versions carry the version they shipped as (tag shipped_as) and link to their
// runs. A run id of a manifest names the run in the store it was trained in; a store restored from the committed
// snapshot holds that run under another id, so a direct run link would not find it.
export function runUrl(uiUrl, name, mlflow) {
  if (!mlflow || !mlflow.run_id) return null;
  return `${uiUrl}/#/models/${encodeURIComponent(name)}`;
}

function evaluation(e) {
  const metrics = Object.entries(e.metrics || {});
  const headline = metrics.slice(0, HEADLINE_METRICS).map(([k, v]) => `${k} ${fmt(v, 4)}`).join(", ");
  const list = el("dl");
  for (const [k, v] of metrics) list.append(el("dt", { textContent: k }), el("dd", { textContent: fmt(v, 4) }));
  const more = metrics.length > HEADLINE_METRICS ? ` … (${metrics.length})` : "";
  return el(
    "details",
    {},
    el("summary", { textContent: `${e.name}: ${headline}${more}` }),
    list,
    el("code", { textContent: e.command || "" }),
  );
}

export function renderModels(tbody, models, uiUrl) {
  tbody.replaceChildren();
  for (const [name, m] of Object.entries(models).sort(([a], [b]) => a.localeCompare(b))) {
    const url = runUrl(uiUrl, name, m.mlflow);
    const run = url ? el("a", { href: url, textContent: m.mlflow.run_id.slice(0, 8) }) : "–";
    const evaluations = el("td", {}, ...(m.evaluations || []).map(evaluation));
    tbody.append(
      el(
        "tr",
        { dataset: { model: name } },
        el("td", { textContent: name, title: m.source || "" }),
        el("td", { textContent: m.version }),
        el("td", { textContent: m.task }),
        evaluations,
        el("td", {}, run),
      ),
    );
  }
}
