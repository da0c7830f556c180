// The live view: the loaded models, and a real recording played through the service's own streams.
import { KneeChart } from "./chart.js";
import { byId, el, fmt } from "./dom.js";
import { loadModels, renderModels } from "./models.js";
import { loadRecording, Player } from "./player.js";

const page = {
  config: null, models: null, recording: null, player: null, figure: null, chart: null, plan: null, rows: {},
};

const POSE_RATE_HZ = 60; // pose streams answer every frame at the model rate (service.api.protocol)
const POSE_KNEES =
  "dashed: the pose stream's knees once the assignment has handed its sensors over (between its thighs and " +
  "shanks: the thigh sensors' own where the assignment placed them, as on this recording, else the model's thighs)";
const HEADINGS = {
  both: "Knee flexion: the capacitive sleeves and the IMU pose",
  flex: "Knee flexion from the capacitive sleeves",
  pose: "Knee flexion from the IMU pose",
};

async function init() {
  page.config = await (await fetch("/dashboard/config.json")).json();
  byId("mlflow-link").href = page.config.ui_url;
  const speed = new URLSearchParams(location.search).get("speed");
  if (speed) byId("speed").value = speed;
  byId("key-form").addEventListener("submit", (event) => {
    event.preventDefault();
    refreshModels();
  });
  byId("play").addEventListener("click", play);
  byId("stop").addEventListener("click", () => page.player && page.player.stop());
  page.recording = await loadRecording();
  showRecording(page.recording.meta);
  await refreshModels();
}

async function refreshModels() {
  const note = byId("models-note");
  try {
    page.models = await loadModels(byId("key").value.trim());
    renderModels(document.querySelector("#models tbody"), page.models, page.config.ui_url);
    note.textContent = "Each manifest's evaluation figures, with the command that produced them (open a row).";
    byId("play").disabled = false;
    trainedOn(page.recording.meta);
  } catch (err) {
    note.textContent = err.message;
    byId("play").disabled = true;
  }
  if (page.config.key_required) {
    note.textContent += " This service has an API key: the field above gives it to /v1/models and to the streams.";
  }
}

function showRecording(meta) {
  byId("recording").textContent = `${meta.description}. ${meta.citation}; MIT licence (recording.LICENSE).`;
  const tbody = document.querySelector("#sensors tbody");
  for (const s of meta.imu.sensors) {
    const cell = (field) => el("td", { dataset: { field }, className: "num", textContent: "–" });
    const row = el("tr", { dataset: { sensor: s.sensor_id } }, el("td", { textContent: s.sensor_id }));
    row.append(el("td", { textContent: s.segment }));
    for (const field of ["segment", "p_correct", "committed", "confidence", "windows", "moment"]) row.append(cell(field));
    page.rows[s.sensor_id] = { row, label: s.segment };
    tbody.append(row);
  }
}

function trainedOn(meta) {
  // meta.name is "<source>/<trial>": the I2S models list their real recordings, the capacitive ones source and trials
  const [source, trial] = meta.name.split("/");
  const seen = Object.values(page.models).filter((m) => {
    const data = m.training_data || {};
    if ((data.real_train_recordings || []).includes(meta.name)) return true;
    const trials = data.train_trials || (data.train_trial ? [data.train_trial] : []);
    return (data.sources || []).includes(source) && trials.includes(trial);
  });
  if (seen.length) {
    const names = seen.map((m) => `${m.name} ${m.version}`).join(", ");
    byId("recording").textContent +=
      ` The served ${names} ${seen.length > 1 ? "were" : "was"} trained on this recording too: this view shows the` +
      " service at work, not a held-out figure (those are in the manifests above).";
  }
}

function plan() {
  const { meta } = page.recording;
  const worn = meta.imu.sensors.map((s) => s.segment);
  const models = Object.values(page.models);
  const pose = models.some((m) => m.task === "imu_pose" && m.pose && m.pose.streaming && m.pose.sensors.every((s) => worn.includes(s)));
  const flex = models.find((m) => m.task === "flex_pose" && JSON.stringify(m.channels) === JSON.stringify(meta.flex.channels));
  return { pose, flexModel: flex ? flex.name : null, flexRateHz: flex ? flex.sample_rate_hz : 0 };
}

async function play() {
  const p = plan();
  byId("log").textContent = "";
  byId("pose-panel").hidden = !p.pose;
  byId("flex-panel").hidden = !p.flexModel && !p.pose;
  if (p.pose && !page.figure) {
    const { StickFigure } = await import("./figure.js");
    page.figure = new StickFigure(byId("figure"), page.config.body);
  }
  if (p.flexModel || p.pose) page.chart = new KneeChart(byId("flex-chart"));
  page.plan = p;
  byId("flex-heading").textContent = HEADINGS[p.flexModel && p.pose ? "both" : p.flexModel ? "flex" : "pose"];
  byId("flex-note").textContent = p.pose ? POSE_KNEES : "";
  byId("play").disabled = true;
  byId("stop").disabled = false;
  setState("playing");
  page.player = new Player(page.recording, p, {
    message: onMessage,
    flex: onFlex,
    clock: (t) => (byId("clock").textContent = `${t.toFixed(1)} s`),
    closed: (path, code, reason) => code !== 1000 && log(`${path} closed with ${code}${reason ? `: ${reason}` : ""}`),
    done: () => {
      setState("done");
      byId("play").disabled = false;
      byId("stop").disabled = true;
    },
  }, byId("key").value.trim());
  page.player.play(Number(byId("speed").value));
}

function setState(state) {
  document.body.dataset.state = state;
  byId("state").textContent = state;
}

function log(text) {
  byId("log").textContent += `${text}\n`;
}

function setCell(sensorId, field, text, className = "num") {
  const cell = page.rows[sensorId].row.querySelector(`[data-field="${field}"]`);
  cell.textContent = text;
  cell.className = className;
}

function onMessage(m) {
  if (m.type === "assignment") {
    byId("status").textContent = m.status;
    byId("p-all").textContent = fmt(m.p_all_correct);
    byId("p-all-wrap").hidden = m.p_all_correct === null || m.p_all_correct === undefined;  // per-sensor models: none
    byId("dropped").textContent = m.results_dropped;
    for (const s of m.sensors) {
      const right = s.segment === page.rows[s.sensor_id].label;
      setCell(s.sensor_id, "segment", s.segment || "–", s.segment ? (right ? "right" : "wrong") : "");
      setCell(s.sensor_id, "p_correct", fmt(s.p_correct));
      setCell(s.sensor_id, "committed", s.committed === null || s.committed === undefined ? "–" : s.committed ? "yes" : "no", "");
      setCell(s.sensor_id, "confidence", fmt(s.confidence));
      setCell(s.sensor_id, "windows", String(s.windows));
    }
  } else if (m.type === "moment") {
    for (const [id, segment] of Object.entries(m.segments)) setCell(id, "moment", segment || "–", "");
  } else if (m.type === "started" && m.pose) {
    byId("pose-note").textContent = `${m.pose.model} ${m.pose.version} on ${m.pose.sensors.join(", ")}: waiting for the assignment to place them`;
  } else if (m.type === "calibration" && m.status === "calibrated") {
    const placed = Object.entries(m.segments).map(([id, seg]) => `${id} → ${seg}`).join(", ");
    byId("pose-note").textContent = `calibrated by the assignment: ${placed}`;
  } else if (m.type === "pose") {
    const canvas = byId("figure");
    canvas.dataset.frames = Number(canvas.dataset.frames) + m.frames;
    page.figure.show(m.joint_positions_m.at(-1), m.q_world_segment.at(-1)[0]);
    for (const side of ["Left", "Right"]) {
      const knee = (m.joint_angles_deg || {})[`${side}Knee`];
      if (knee) page.chart.push(`${side} knee, IMU pose`, side, POSE_RATE_HZ, knee.map((frame) => frame[0]), true);
    }
  } else if (m.type === "error") {
    log(`/v1/stream: ${m.detail}`);
  }
}

function onFlex(side, m) {
  if (m.type === "started") {
    const sleeves = `solid: ${m.model} ${m.version}, each sleeve's seven channels → knee flexion (°)`;
    byId("flex-note").textContent = page.plan.pose ? `${sleeves}; ${POSE_KNEES}` : sleeves;
  } else if (m.type === "angles") {
    page.chart.push(`${side} knee, sleeve`, side, page.plan.flexRateHz, m.angles_deg.map((frame) => frame[0][0]));
  } else if (m.type === "warning") {
    log(`/v1/stream/flex (${side}): ${m.warnings.join("; ")}`);
  } else if (m.type === "error") {
    log(`/v1/stream/flex (${side}): ${m.detail}`);
  }
}

init().catch((err) => log(`the page could not start: ${err.message}`));
