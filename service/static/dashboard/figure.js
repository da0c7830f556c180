// A 3D stick figure of the pose messages (three.js): a bone from each segment's origin to its parent's
// (joint_positions_m, z up, pelvis at the origin); the camera follows the pelvis's heading.
import * as THREE from "./vendor/three.module.min.js";

const COLOURS = { Left: 0x2563eb, Right: 0xea580c, Centre: 0x555555 };
const Y = new THREE.Vector3(0, 1, 0);

function side(segment) {
  return segment.startsWith("Left") ? "Left" : segment.startsWith("Right") ? "Right" : "Centre";
}

export class StickFigure {
  // body: {segments, parents} (GET /dashboard/config.json)
  constructor(canvas, body) {
    this.parents = body.parents;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0xf6f7f9);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x999999, 3));
    this.camera = new THREE.PerspectiveCamera(30, canvas.width / canvas.height, 0.1, 50);
    this.camera.up.set(0, 0, 1);
    this.floor = new THREE.GridHelper(4, 16, 0x999999, 0xdddddd);
    this.floor.rotation.x = Math.PI / 2; // the grid lies in x-z; the world is z up
    this.floor.position.z = -0.95;
    this.scene.add(this.floor);
    const material = (segment) => new THREE.MeshLambertMaterial({ color: COLOURS[side(segment)] });
    this.joints = body.segments.map((segment) => this.add(new THREE.SphereGeometry(0.03, 12, 8), material(segment)));
    this.bones = body.segments.map((segment, i) =>
      body.parents[i] < 0 ? null : this.add(new THREE.CylinderGeometry(0.018, 0.018, 1, 8), material(segment)),
    );
    this.heading = 0;
    this.latest = null;
    this.follow(0);
    this.renderer.render(this.scene, this.camera);
  }

  add(geometry, material) {
    const mesh = new THREE.Mesh(geometry, material);
    mesh.visible = false;
    this.scene.add(mesh);
    return mesh;
  }

  // positions: one [x, y, z] per segment (m); qPelvis: the pelvis's q_world_segment (w, x, y, z)
  show(positions, qPelvis) {
    if (!this.latest) requestAnimationFrame(() => this.draw());
    this.latest = { positions, qPelvis };
  }

  draw() {
    const { positions, qPelvis } = this.latest;
    this.latest = null;
    const p = positions.map(([x, y, z]) => new THREE.Vector3(x, y, z));
    p.forEach((v, i) => {
      this.joints[i].position.copy(v);
      this.joints[i].visible = true;
    });
    this.bones.forEach((bone, i) => {
      if (!bone) return;
      const d = new THREE.Vector3().subVectors(p[i], p[this.parents[i]]);
      const length = d.length();
      bone.visible = length > 1e-4;
      if (!bone.visible) return;
      bone.position.addVectors(p[i], p[this.parents[i]]).multiplyScalar(0.5);
      bone.scale.set(1, length, 1);
      bone.quaternion.setFromUnitVectors(Y, d.divideScalar(length));
    });
    this.floor.position.z = Math.min(...p.map((v) => v.z));
    const [w, x, y, z] = qPelvis;
    const heading = Math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z)); // the pelvis x axis (anterior)
    this.heading += 0.1 * Math.atan2(Math.sin(heading - this.heading), Math.cos(heading - this.heading));
    this.follow(this.heading);
    this.renderer.render(this.scene, this.camera);
  }

  follow(heading) {
    const a = heading + 0.7; // seen from 40° to the body's left
    this.camera.position.set(3.6 * Math.cos(a), 3.6 * Math.sin(a), 0.25);
    this.camera.lookAt(0, 0, -0.3);
  }
}
