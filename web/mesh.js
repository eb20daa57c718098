/* Triangle meshes read in the browser (OBJ, ASCII or binary STL, ASCII or binary PLY), enough for the
 * new-survey form to show a specimen model and pick its vertices: vertex positions and triangles only
 * (polygons are fanned into triangles; normals, colours and texture coordinates are ignored).
 *
 * It follows the API's reader (workers/algorithms/mesh.py), so a file that parses here parses there and a
 * file refused here gets the message the API would give, before anything is uploaded. No DOM: node runs it.
 */

export const MESH_SUFFIXES = [".obj", ".ply", ".stl"];
const MAX_TRIANGLES = 2_000_000; // as the API

/** The file is not a mesh this module reads; the message says where it went wrong. */
export class MeshError extends Error {}

/**
 * Parse `buffer` (an ArrayBuffer) as the format `name`'s suffix says.
 * Answers { vertices: Float64Array (3V: x, y, z mm), triangles: Uint32Array (3T vertex indices) }.
 */
export function parseMesh(buffer, name) {
  const suffix = (/\.[^.]*$/.exec(name) || [""])[0].toLowerCase();
  const readers = { ".obj": readObj, ".ply": readPly, ".stl": readStl };
  if (!readers[suffix]) throw new MeshError(`${name}: unknown model format; use one of ${MESH_SUFFIXES.join(", ")}`);
  let mesh;
  try {
    mesh = readers[suffix](new Uint8Array(buffer));
  } catch (err) {
    if (err instanceof MeshError) throw new MeshError(`${name}: ${err.message}`);
    if (err instanceof RangeError) throw new MeshError(`${name}: not a valid ${suffix.slice(1).toUpperCase()} file (it ends too early)`);
    throw err;
  }
  return checked(name, mesh);
}

/** { min: [x, y, z], max: [x, y, z] } of the vertices, mm. */
export function meshBounds(vertices) {
  const min = [Infinity, Infinity, Infinity];
  const max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < vertices.length; i += 3) {
    for (let a = 0; a < 3; a += 1) {
      const v = vertices[i + a];
      if (v < min[a]) min[a] = v;
      if (v > max[a]) max[a] = v;
    }
  }
  return { min, max };
}

function checked(name, { vertices, triangles }) {
  const fail = (message) => { throw new MeshError(`${name}: ${message}`); };
  if (!triangles.length) fail("the model has no triangles");
  if (triangles.length / 3 > MAX_TRIANGLES) fail(`${triangles.length / 3} triangles; at most ${MAX_TRIANGLES} are accepted`);
  if (!vertices.every(Number.isFinite)) fail("some vertex coordinates are not finite numbers");
  const count = vertices.length / 3;
  if (!triangles.every((i) => Number.isInteger(i) && i >= 0 && i < count)) {
    fail(`a face refers to a vertex that does not exist (${count} vertices)`);
  }
  return { vertices: Float64Array.from(vertices), triangles: Uint32Array.from(triangles) };
}

function fan(polygon, out) {
  for (let k = 1; k < polygon.length - 1; k += 1) out.push(polygon[0], polygon[k], polygon[k + 1]);
}

function number(text, where) {
  const value = Number(text);
  if (text === undefined || text === "" || Number.isNaN(value)) throw new MeshError(`${where}: '${text ?? ""}' is not a number`);
  return value;
}

// -- OBJ -------------------------------------------------------------------------------------------

function readObj(bytes) {
  const vertices = [];
  const triangles = [];
  const lines = new TextDecoder().decode(bytes).split(/\r\n|\r|\n/);
  lines.forEach((raw, i) => {
    const parts = raw.split("#", 1)[0].trim().split(/\s+/);
    const where = `line ${i + 1}`;
    if (parts[0] === "v") {
      if (parts.length < 4) throw new MeshError(`${where}: a vertex needs x y z`);
      vertices.push(number(parts[1], where), number(parts[2], where), number(parts[3], where));
    } else if (parts[0] === "f") {
      if (parts.length < 4) throw new MeshError(`${where}: a face needs at least three vertices`);
      // "f v/vt/vn ...": 1-based, negative counts back from the last vertex read so far
      const seen = vertices.length / 3;
      fan(parts.slice(1).map((p) => {
        const index = p.split("/")[0];
        if (!/^[+-]?\d+$/.test(index)) throw new MeshError(`${where}: '${p}' is not a vertex index`);
        const n = Number(index);
        return n > 0 ? n - 1 : seen + n;
      }), triangles);
    }
  });
  return { vertices, triangles };
}

// -- STL -------------------------------------------------------------------------------------------

function readStl(bytes) {
  // A binary STL may begin with "solid" too: it is binary when its size matches its triangle count.
  if (bytes.length >= 84) {
    const data = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const count = data.getUint32(80, true);
    if (bytes.length === 84 + 50 * count) {
      const corners = new Float64Array(9 * count);
      for (let t = 0; t < count; t += 1) {
        for (let j = 0; j < 9; j += 1) corners[9 * t + j] = data.getFloat32(84 + 50 * t + 12 + 4 * j, true);
      }
      return weld(corners);
    }
  }
  const text = new TextDecoder().decode(bytes);
  if (!text.trimStart().startsWith("solid")) {
    throw new MeshError("neither a binary STL (its size does not match its triangle count) nor an ASCII one");
  }
  const corners = [];
  for (const m of text.matchAll(/vertex\s+(\S+)\s+(\S+)\s+(\S+)/g)) corners.push(...m.slice(1).map((t) => number(t, "a vertex")));
  if (corners.length % 9) throw new MeshError(`${corners.length / 3} vertices is not a whole number of triangles`);
  return weld(corners);
}

/** STL stores every triangle's corners: shared vertices are merged so the mesh is connected. */
function weld(corners) {
  const index = new Map();
  const vertices = [];
  const triangles = [];
  for (let i = 0; i < corners.length; i += 3) {
    const key = `${corners[i]},${corners[i + 1]},${corners[i + 2]}`;
    let k = index.get(key);
    if (k === undefined) {
      k = vertices.length / 3;
      index.set(key, k);
      vertices.push(corners[i], corners[i + 1], corners[i + 2]);
    }
    triangles.push(k);
  }
  return { vertices, triangles };
}

// -- PLY -------------------------------------------------------------------------------------------

// type -> [DataView getter, bytes]
const PLY_TYPES = {
  char: ["Int8", 1], int8: ["Int8", 1], uchar: ["Uint8", 1], uint8: ["Uint8", 1], short: ["Int16", 2], int16: ["Int16", 2],
  ushort: ["Uint16", 2], uint16: ["Uint16", 2], int: ["Int32", 4], int32: ["Int32", 4], uint: ["Uint32", 4], uint32: ["Uint32", 4],
  float: ["Float32", 4], float32: ["Float32", 4], double: ["Float64", 8], float64: ["Float64", 8],
};

function readPly(bytes) {
  const head = new TextDecoder("latin1").decode(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const end = head.indexOf("end_header");
  if (!head.startsWith("ply") || end < 0) {
    throw new MeshError("no PLY header (it must start with 'ply' and close with 'end_header')");
  }
  const newline = head.indexOf("\n", end);
  const body = bytes.subarray(newline < 0 ? bytes.length : newline + 1);
  const { format, elements } = plyHeader(head.slice(0, end).split(/\r?\n/));
  const rows = format === "ascii" ? plyAscii(new TextDecoder().decode(body)) : plyBinary(body, format === "binary_little_endian");
  const vertices = [];
  const triangles = [];
  for (const element of elements) {
    for (let r = 0; r < element.count; r += 1) {
      const row = {};
      for (const property of element.properties) row[property.name] = rows.read(property);
      if (element.name === "vertex") vertices.push(row.x, row.y, row.z);
      else if (element.name === "face") {
        const polygon = row.vertex_indices ?? row.vertex_index;
        if (!Array.isArray(polygon)) throw new MeshError("a PLY face needs a 'vertex_indices' list");
        fan(polygon, triangles);
      }
    }
  }
  return { vertices, triangles };
}

function plyHeader(lines) {
  let format = "";
  const elements = [];
  for (const line of lines.slice(1)) {
    const parts = line.trim().split(/\s+/);
    if (parts[0] === "format") format = parts[1];
    else if (parts[0] === "element") elements.push({ name: parts[1], count: Number(parts[2]), properties: [] });
    else if (parts[0] === "property" && elements.length) {
      const list = parts[1] === "list";
      const [countType, type, name] = list ? parts.slice(2, 5) : [null, parts[1], parts[2]];
      if (!PLY_TYPES[type] || (list && !PLY_TYPES[countType])) throw new MeshError(`unknown PLY property type in '${line.trim()}'`);
      elements[elements.length - 1].properties.push({ name, type: PLY_TYPES[type], count: list ? PLY_TYPES[countType] : null });
    }
  }
  if (!["ascii", "binary_little_endian", "binary_big_endian"].includes(format)) throw new MeshError(`unknown PLY format '${format}'`);
  const names = elements.map((e) => e.name);
  if (!names.includes("vertex") || !names.includes("face")) throw new MeshError("a PLY model needs 'vertex' and 'face' elements");
  if (!elements.every((e) => Number.isInteger(e.count) && e.count >= 0)) throw new MeshError("an element count is not a whole number");
  return { format, elements };
}

/** A reader of the body's values in order: `read(property)` answers a number, or an array for a list. */
function plyAscii(text) {
  const tokens = text.split(/\s+/).filter(Boolean);
  let at = 0;
  const next = () => {
    if (at >= tokens.length) throw new MeshError("not a valid PLY file (it ends too early)");
    return number(tokens[at++], `value ${at}`);
  };
  return {
    read(property) {
      if (!property.count) return next();
      const n = next();
      return Array.from({ length: n }, () => Math.trunc(next()));
    },
  };
}

function plyBinary(body, little) {
  const data = new DataView(body.buffer, body.byteOffset, body.byteLength);
  let at = 0;
  const next = ([getter, size]) => {
    const value = data[`get${getter}`](at, little); // a RangeError past the end: "it ends too early"
    at += size;
    return value;
  };
  return {
    read(property) {
      if (!property.count) return next(property.type);
      const n = next(property.count);
      return Array.from({ length: n }, () => next(property.type));
    },
  };
}
