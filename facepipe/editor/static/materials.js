// The editor's materials: the face (Lambert shading, lit per vertex) and the handle markers (round
// points). Both are chosen for a software rasteriser (a machine without a GPU), which pays per
// vertex, per triangle, per varying and per shaded pixel.
//
// The face: its lighting (shading.js: what three.js's MeshLambertMaterial draws with the same
// lights) is evaluated per vertex in JavaScript where the normals are made, as colours in the
// output's colour space, front and back (both sides are lit: the inside of lips and eyelids
// shows); the shaders only place the vertices and interpolate those colours. Lambert lighting
// does not depend on the view, so orbiting needs no new colours.
import * as THREE from 'three';

const vertexShader = /* glsl */ `
attribute vec4 front;  // normalised bytes: the lit colour of front faces, sRGB
attribute vec4 back;
varying vec3 vFront;
varying vec3 vBack;

void main() {
  vFront = front.rgb;
  vBack = back.rgb;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

const fragmentShader = /* glsl */ `
varying vec3 vFront;
varying vec3 vBack;

void main() {
  gl_FragColor = vec4(gl_FrontFacing ? vFront : vBack, 1.0);  // already in the output's colour space
}`;

// the face's material: positions and the attributes front and back (Uint8 RGBA, normalised)
export function faceMaterial() {
  return new THREE.ShaderMaterial({ vertexShader, fragmentShader, side: THREE.DoubleSide });
}

// the lights of lightVertices (shading.js) as plain numbers in linear light, three.js's working
// colour space: keyDirection, up (THREE.Vector3, world space, normalised here)
export function faceLight(keyDirection, up, { key = 2.2, sky = 0xffffff, ground = 0x404040, hemisphere = 0.6 } = {}) {
  const rgb = (c) => [c.r, c.g, c.b];
  return {
    key: keyDirection.clone().normalize().toArray(), up: up.clone().normalize().toArray(),
    keyColour: rgb(new THREE.Color(0xffffff).multiplyScalar(key)),
    sky: rgb(new THREE.Color(sky).multiplyScalar(hemisphere)),
    ground: rgb(new THREE.Color(ground).multiplyScalar(hemisphere)),
  };
}

const markerVertexShader = /* glsl */ `
uniform float radius;          // world units
uniform float pixelsPerUnit;   // the drawing buffer's height / (2 tan(fov / 2)): pixels per unit at depth 1
attribute vec3 markerColour;
varying vec3 vColour;

void main() {
  vec4 view = modelViewMatrix * vec4(position, 1.0);
  // drawn at the front of the marker's sphere: the surface through its centre hides no part of it
  view.xyz += normalize(-view.xyz) * radius;
  gl_Position = projectionMatrix * view;
  gl_PointSize = max(2.0, 2.0 * radius * pixelsPerUnit / max(-view.z, 1e-6));
  vColour = markerColour;
}`;

const markerFragmentShader = /* glsl */ `
varying vec3 vColour;

void main() {
  vec2 p = 2.0 * gl_PointCoord - 1.0;
  if (dot(p, p) > 1.0) discard;  // round
  gl_FragColor = vec4(vColour, 1.0);
  #include <colorspace_fragment>
}`;

// The handle markers as points (one vertex each, where spheres cost as many triangles as the
// face): discs of ``radius`` world units, coloured per point by the attribute markerColour.
export function markerMaterial(radius) {
  return new THREE.ShaderMaterial({
    vertexShader: markerVertexShader, fragmentShader: markerFragmentShader,
    uniforms: { radius: { value: radius }, pixelsPerUnit: { value: 1 } },
  });
}
