// The editor's materials: the face (Lambert shading, lit per vertex) and the handle markers (round
// points). Both are chosen for a software rasteriser (a machine without a GPU), which pays per
// vertex, per triangle and per shaded pixel.
//
// The face: Lambert shading of a hemisphere light and a key light, lit per vertex.
//
// It draws what three.js's MeshLambertMaterial draws with the same lights (colour/π × (key × n·l
// + the hemisphere's mix of ground and sky by n·up), in linear light, then the output's colour
// space), but evaluates the lighting in the vertex shader: a software rasteriser (no GPU) pays
// per shaded pixel, the face has fewer vertices than the canvas has pixels, and the wrinkles are
// in the vertex normals either way. Both sides are lit (the inside of lips and eyelids shows).
import * as THREE from 'three';

const vertexShader = /* glsl */ `
uniform vec3 keyDirection;   // towards the key light, world space
uniform vec3 keyColour;
uniform vec3 upDirection;    // the hemisphere light's sky direction, world space
uniform vec3 skyColour;
uniform vec3 groundColour;
varying vec3 vFront;
varying vec3 vBack;

vec3 irradiance(vec3 n) {
  vec3 hemisphere = mix(groundColour, skyColour, 0.5 * dot(n, upDirection) + 0.5);
  return keyColour * max(dot(n, keyDirection), 0.0) + hemisphere;
}

void main() {
  vec3 n = normalize(mat3(modelMatrix) * normal);
  vec3 albedo = color * 0.3183098861837907;  // 1/π: Lambert's BRDF
  vFront = albedo * irradiance(n);
  vBack = albedo * irradiance(-n);
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

const fragmentShader = /* glsl */ `
varying vec3 vFront;
varying vec3 vBack;

void main() {
  gl_FragColor = vec4(gl_FrontFacing ? vFront : vBack, 1.0);
  #include <colorspace_fragment>
}`;

// keyDirection, up: THREE.Vector3 in world space (normalised here)
export function faceMaterial(keyDirection, up, { key = 2.2, sky = 0xffffff, ground = 0x404040, hemisphere = 0.6 } = {}) {
  return new THREE.ShaderMaterial({
    vertexShader, fragmentShader, vertexColors: true, side: THREE.DoubleSide,
    uniforms: {
      keyDirection: { value: keyDirection.clone().normalize() },
      keyColour: { value: new THREE.Color(0xffffff).multiplyScalar(key) },
      upDirection: { value: up.clone().normalize() },
      skyColour: { value: new THREE.Color(sky).multiplyScalar(hemisphere) },
      groundColour: { value: new THREE.Color(ground).multiplyScalar(hemisphere) },
    },
  });
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
