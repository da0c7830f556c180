// The bundled recording (written by scripts/dashboard_recording.py) and the streams that play it to the service:
// the IMUs through /v1/stream, each capacitive sleeve through /v1/stream/flex, sent by this page as binary packets
// at real time (times the chosen speed).

const BASE = "/static/dashboard/";
const TICK_MS = 100;

export async function loadRecording() {
  const [meta, buffer] = await Promise.all([
    fetch(`${BASE}recording.json`).then((r) => r.json()),
    fetch(`${BASE}recording.bin`).then((r) => r.arrayBuffer()),
  ]);
  const view = new DataView(buffer);
  const values = new Float32Array(buffer.byteLength / 4).map((_, i) => view.getFloat32(4 * i, true));
  const { frames } = meta.imu;
  const width = meta.imu.values.length;
  const channels = meta.flex.channels.length;
  const imuEnd = meta.imu.sensors.length * frames * width;
  return {
    meta,
    imu: (k, a, b) => values.subarray((k * frames + a) * width, (k * frames + b) * width),
    sleeve: (j, a, b) => values.subarray(imuEnd + (j * meta.flex.readings + a) * channels, imuEnd + (j * meta.flex.readings + b) * channels),
  };
}

// Binary sample packet of both stream protocols (little-endian): uint16 index, uint16 n, uint32 seq, then n rows
// of float32; `rows` holds n rows of `width` values, of which the first `keep` are sent.
function packet(index, seq, rows, width, keep) {
  const n = rows.length / width;
  const view = new DataView(new ArrayBuffer(8 + 4 * n * keep));
  view.setUint16(0, index, true);
  view.setUint16(2, n, true);
  view.setUint32(4, seq, true);
  for (let i = 0; i < n; i++) {
    for (let c = 0; c < keep; c++) view.setFloat32(8 + 4 * (i * keep + c), rows[i * width + c], true);
  }
  return view.buffer;
}

// A browser cannot set X-API-Key on a WebSocket: the key travels as the subprotocol wearmocap.key.<base64url>.
function keyProtocols(key) {
  if (!key) return [];
  const b64 = btoa(String.fromCharCode(...new TextEncoder().encode(key)));
  return [`wearmocap.key.${b64.replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "")}`];
}

function open(path, start, onMessage, onClose, key) {
  const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${path}`;
  const ws = new WebSocket(url, keyProtocols(key));
  ws.binaryType = "arraybuffer";
  ws.onopen = () => ws.send(JSON.stringify(start));
  ws.onmessage = (event) => onMessage(JSON.parse(event.data));
  ws.onclose = (event) => onClose(event.code, event.reason);
  return ws;
}

export class Player {
  // plan: {pose: a streaming pose model can take the recording's sensors, flexModel: the flex model's name or
  // null}; on: {message(m), flex(side, m), clock(seconds), closed(path, code, reason), done()}
  constructor(recording, plan, on, key) {
    this.key = key;
    this.recording = recording;
    this.plan = plan;
    this.on = on;
    this.streams = [];
    this.timer = null;
  }

  play(speed) {
    const { meta } = this.recording;
    const start = {
      type: "start",
      sensors: meta.imu.sensors.map((s) => ({ sensor_id: s.sensor_id, sample_rate_hz: meta.imu.sample_rate_hz })),
    };
    // No sensor's segment is declared: the stream's own assignment places them and hands its alignments to the pose.
    // joint_angles: the pose's knees are drawn beside the sleeves' answers.
    if (this.plan.pose) start.pose = { calibration: "assignment", joint_angles: true };
    const imu = { path: "/v1/stream", rate: meta.imu.sample_rate_hz, total: meta.imu.frames, sent: 0 };
    imu.ws = open(imu.path, start, (m) => this.on.message(m), (c, r) => this.closed(imu, c, r), this.key);
    this.streams = [imu];
    if (this.plan.flexModel) {
      meta.flex.sides.forEach((side, j) => {
        const flexStart = {
          type: "start",
          model: this.plan.flexModel,
          channels: meta.flex.channels,
          sample_rate_hz: meta.flex.sample_rate_hz,
        };
        const sleeve = { path: "/v1/stream/flex", side: j, rate: meta.flex.sample_rate_hz, total: meta.flex.readings, sent: 0 };
        sleeve.ws = open(sleeve.path, flexStart, (m) => this.on.flex(side, m), (c, r) => this.closed(sleeve, c, r), this.key);
        this.streams.push(sleeve);
      });
    }
    this.t0 = performance.now();
    this.speed = speed;
    this.timer = setInterval(() => this.tick(), TICK_MS);
  }

  tick() {
    const t = ((performance.now() - this.t0) / 1000) * this.speed;
    const { meta } = this.recording;
    for (const s of this.streams) {
      if (s.stopped || s.ws.readyState !== WebSocket.OPEN) continue;
      const until = Math.min(s.total, Math.floor(t * s.rate));
      if (until > s.sent) this.send(s, until);
      if (s.sent >= s.total) this.stopStream(s);
    }
    this.on.clock(Math.min(t, meta.imu.frames / meta.imu.sample_rate_hz));
    if (this.streams.every((s) => s.stopped || s.closed)) clearInterval(this.timer);
  }

  send(s, until) {
    const width = this.recording.meta.imu.values.length;
    if (s.side === undefined) {
      this.recording.meta.imu.sensors.forEach((_, k) => {
        const rows = this.recording.imu(k, s.sent, until);
        s.ws.send(packet(k, s.sent, rows, width, this.plan.pose ? width : 6));
      });
    } else {
      const channels = this.recording.meta.flex.channels.length;
      s.ws.send(packet(0, s.sent, this.recording.sleeve(s.side, s.sent, until), channels, channels));
    }
    s.sent = until;
  }

  stopStream(s) {
    s.stopped = true;
    if (s.ws.readyState === WebSocket.OPEN) s.ws.send(JSON.stringify({ type: "stop" }));
  }

  stop() {
    clearInterval(this.timer);
    this.streams.forEach((s) => this.stopStream(s));
  }

  closed(s, code, reason) {
    s.closed = true;
    this.on.closed(s.path, code, reason);
    if (this.streams.every((x) => x.closed)) {
      clearInterval(this.timer);
      this.on.done();
    }
  }
}
