//! Triangle-mesh obstacles: Wavefront OBJ and STL (binary or ASCII) files, scaled and placed,
//! ray cast exactly through a bounding-volume hierarchy and voxelised on the scenario's grid.
//!
//! - Reading. [`TriangleMesh::from_stl`] tells binary from ASCII by size: a file exactly 84 bytes
//!   plus 50 per triangle its header announces is binary, whatever its 80-byte header says (even
//!   `solid …`), and is read by the [`stl_io`] crate; one announcing no triangle is an error.
//!   Anything else must be UTF-8 text, read as ASCII STL: every `vertex x y z` line, three to a
//!   facet, whatever surrounds them. [`TriangleMesh::from_obj`] reads `v` and `f` records
//!   (polygons become triangle fans (v0, vi, vi+1); `f` indices may be `v`, `v/t`, `v//n`,
//!   `v/t/n`, negative = relative; a face needs three corners; coordinates must be finite);
//!   everything else, `l` polylines and `mtllib` included, is ignored. Errors name the line.
//!   Every triangle keeps its corners in file order and degenerate ones are kept.
//!
//!   OBJ and ASCII STL stay hand-written because the maintained crates would change what loads
//!   (checked against `tobj` 4.0.5 and `stl_io` 0.11.0; the tests
//!   `obj_reads_faces_only_and_names_the_bad_line` and `ascii_stl_reads_every_facet` pin it):
//!   - `tobj` reports errors as a bare enum with no position, so `line 2: face index 2 refers to
//!     no vertex` would become `face vertex index out of bounds`; it reads `l` polylines of three
//!     or more points as faces (obstacles that are not there), silently drops one- and
//!     two-corner faces, accepts `nan` and `inf` coordinates, divides `v x y z w` by `w`, and
//!     rejects files that load here (a one-component `vt`, a `vt` index out of range, a bare
//!     `usemtl`). Its fan order, relative indices and missing material libraries do match.
//!   - `stl_io`'s ASCII reader stops at the first `endsolid`, silently dropping the other solids
//!     of a multi-solid file; takes a nameless or indented `solid` line for binary (and fails
//!     with "failed to fill whole buffer"); requires `endsolid`; and names no line in errors.
//!     Its own binary/ASCII test (first line starts with `solid `) misreads a binary file whose
//!     header starts so when the bytes up to the first line feed are UTF-8 (10 triangles: the
//!     count's low byte is a line feed), hence the size rule and a blanked header.
//! - [`Bvh`]: a binary tree of boxes over the triangles, split at the median of the longest
//!   axis; leaves hold at most [`LEAF_SIZE`] triangles. Ray casts (Möller–Trumbore) and
//!   closest-point queries visit only the boxes that can matter, so a million triangles cost
//!   microseconds per ray.
//! - [`MeshObject::voxelise`]: a voxel is solid if the surface passes through its interior
//!   (triangle–box separating-axis test on the voxel shrunk by
//!   [`crate::world::aabb::CELL_EPSILON`], so a face lying on a voxel boundary does not claim the
//!   voxel beside it), or — with `fill` — if its centre is inside a closed surface (odd number of
//!   crossings along +x).

use std::path::Path;

use nalgebra::{Point3, Vector3};

use crate::world::aabb::{Aabb, CELL_EPSILON};

/// Most triangles in a BVH leaf.
pub const LEAF_SIZE: usize = 4;

/// A triangle soup in the map frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TriangleMesh {
    /// Vertices, metres.
    pub vertices: Vec<Point3<f32>>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
}

/// Why a mesh could not be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MeshError(pub String);

impl std::fmt::Display for MeshError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl TriangleMesh {
    /// Parses Wavefront OBJ text.
    pub fn from_obj(text: &str) -> Result<Self, MeshError> {
        let mut mesh = TriangleMesh::default();
        let mut face = Vec::with_capacity(8);
        for (k, line) in text.lines().enumerate() {
            let line_no = k + 1;
            let mut parts = line.split_whitespace();
            match parts.next() {
                Some("v") => {
                    let mut c = [0.0f32; 3];
                    for v in c.iter_mut() {
                        let s = parts
                            .next()
                            .ok_or_else(|| MeshError(format!("line {line_no}: vertex needs x y z")))?;
                        *v = s
                            .parse()
                            .map_err(|_| MeshError(format!("line {line_no}: bad coordinate `{s}`")))?;
                    }
                    if !c.iter().all(|x| x.is_finite()) {
                        return Err(MeshError(format!("line {line_no}: coordinate not finite")));
                    }
                    mesh.vertices.push(Point3::from(c));
                }
                Some("f") => {
                    face.clear();
                    let n = mesh.vertices.len() as i64;
                    for p in parts {
                        let first = p.split('/').next().unwrap_or("");
                        let i: i64 = first
                            .parse()
                            .map_err(|_| MeshError(format!("line {line_no}: bad face index `{p}`")))?;
                        let i = if i < 0 { n + i } else { i - 1 };
                        if i < 0 || i >= n {
                            return Err(MeshError(format!(
                                "line {line_no}: face index {p} refers to no vertex ({n} so far)"
                            )));
                        }
                        face.push(i as u32);
                    }
                    if face.len() < 3 {
                        return Err(MeshError(format!("line {line_no}: a face needs 3 vertices")));
                    }
                    for j in 1..face.len() - 1 {
                        mesh.triangles.push([face[0], face[j], face[j + 1]]);
                    }
                }
                _ => {}
            }
        }
        if mesh.triangles.is_empty() {
            return Err(MeshError("no faces".into()));
        }
        Ok(mesh)
    }

    /// Parses an STL file, binary or ASCII.
    pub fn from_stl(bytes: &[u8]) -> Result<Self, MeshError> {
        if let Some(n) = binary_stl_triangles(bytes) {
            // An empty mesh has no hierarchy to build (`Bvh::build` needs a triangle).
            if n == 0 {
                return Err(MeshError("binary STL with no facets".into()));
            }
            return Self::from_binary_stl(bytes, n);
        }
        let text = std::str::from_utf8(bytes).map_err(|_| {
            MeshError("neither binary STL (size does not match the triangle count) nor ASCII".into())
        })?;
        Self::from_ascii_stl(text)
    }

    /// Reads a binary STL of `n` triangles (its size already checked) with `stl_io`.
    fn from_binary_stl(bytes: &[u8], n: usize) -> Result<Self, MeshError> {
        // stl_io reads a file as ASCII if its first line starts with `solid `, which a binary
        // header may (it is free text); the size has said binary, so stl_io gets the file with
        // the header blanked (it skips the header's content anyway).
        let blanked;
        let input = match bytes.split_at_checked(80) {
            Some((header, rest)) if header.trim_ascii_start().starts_with(b"solid") => {
                blanked = [&[b' '; 80][..], rest].concat();
                blanked.as_slice()
            }
            _ => bytes,
        };
        let read_error = |e: std::io::Error| MeshError(format!("binary STL: {e}"));
        let mut cursor = std::io::Cursor::new(input);
        let facets = stl_io::create_stl_reader(&mut cursor).map_err(read_error)?;
        let mut mesh = TriangleMesh {
            vertices: Vec::with_capacity(3 * n),
            triangles: Vec::with_capacity(n),
        };
        for facet in facets {
            let facet = facet.map_err(read_error)?;
            let base = mesh.vertices.len() as u32;
            mesh.vertices.extend(facet.vertices.map(|v| Point3::from(v.0)));
            mesh.triangles.push([base, base + 1, base + 2]);
        }
        if mesh.triangles.len() != n {
            return Err(MeshError(format!(
                "binary STL: {} of the {n} triangles announced were read",
                mesh.triangles.len()
            )));
        }
        Ok(mesh)
    }

    fn from_ascii_stl(text: &str) -> Result<Self, MeshError> {
        let mut mesh = TriangleMesh::default();
        let mut pending = Vec::with_capacity(3);
        for (k, line) in text.lines().enumerate() {
            let mut parts = line.split_whitespace();
            if parts.next() != Some("vertex") {
                continue;
            }
            let mut c = [0.0f32; 3];
            for v in c.iter_mut() {
                let s = parts.next().unwrap_or("");
                *v = s
                    .parse()
                    .map_err(|_| MeshError(format!("line {}: bad vertex coordinate `{s}`", k + 1)))?;
            }
            pending.push(Point3::from(c));
            if pending.len() == 3 {
                let base = mesh.vertices.len() as u32;
                mesh.vertices.append(&mut pending);
                mesh.triangles.push([base, base + 1, base + 2]);
            }
        }
        if mesh.triangles.is_empty() {
            return Err(MeshError("no facets".into()));
        }
        Ok(mesh)
    }

    /// Reads an `.obj` or `.stl` file (by extension).
    pub fn load(path: &Path) -> Result<Self, MeshError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let bytes = std::fs::read(path).map_err(|e| MeshError(format!("cannot read: {e}")))?;
        match ext.as_str() {
            "obj" => {
                let text = String::from_utf8(bytes).map_err(|_| MeshError("OBJ is not UTF-8 text".into()))?;
                Self::from_obj(&text)
            }
            "stl" => Self::from_stl(&bytes),
            _ => Err(MeshError(format!(
                "unknown mesh format `.{ext}` (expected .obj or .stl)"
            ))),
        }
    }

    /// Scales (per axis), rotates about z and translates every vertex, in that order.
    pub fn transform(&mut self, scale: [f32; 3], rotate_z_rad: f32, translate: [f32; 3]) {
        let (s, c) = rotate_z_rad.sin_cos();
        for v in self.vertices.iter_mut() {
            let (x, y, z) = (v.x * scale[0], v.y * scale[1], v.z * scale[2]);
            *v = Point3::new(
                c * x - s * y + translate[0],
                s * x + c * y + translate[1],
                z + translate[2],
            );
        }
    }

    fn corners(&self, t: usize) -> [Point3<f32>; 3] {
        self.triangles[t].map(|i| self.vertices[i as usize])
    }

    /// Unit normal of triangle `t` (right-handed winding), or zero for a degenerate one.
    pub fn triangle_normal(&self, t: usize) -> Vector3<f32> {
        let c = self.corners(t);
        (c[1] - c[0])
            .cross(&(c[2] - c[0]))
            .try_normalize(1e-12)
            .unwrap_or_else(Vector3::zeros)
    }

    /// The box around every vertex.
    pub fn bounds(&self) -> Aabb {
        let mut lo = Point3::from([f32::INFINITY; 3]);
        let mut hi = Point3::from([f32::NEG_INFINITY; 3]);
        for v in &self.vertices {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        Aabb::new(lo, hi)
    }
}

/// The triangle count a binary STL's header announces, if the file is exactly that long
/// (80-byte header, 4-byte count, 50 bytes per triangle).
fn binary_stl_triangles(bytes: &[u8]) -> Option<usize> {
    let count: [u8; 4] = bytes.get(80..84)?.try_into().ok()?;
    let n = u32::from_le_bytes(count) as usize;
    let size = n.checked_mul(50)?.checked_add(84)?;
    (bytes.len() == size).then_some(n)
}

#[derive(Debug, Clone)]
struct Node {
    bounds: Aabb,
    /// Leaf: first triangle (in `order`) and count; inner: `count == 0` and `first` is the
    /// right child (the left child follows the node).
    first: u32,
    count: u32,
}

/// A bounding-volume hierarchy over a mesh's triangles.
#[derive(Debug, Clone)]
pub struct Bvh {
    nodes: Vec<Node>,
    order: Vec<u32>,
}

fn triangle_bounds(c: &[Point3<f32>; 3]) -> Aabb {
    let mut lo = c[0];
    let mut hi = c[0];
    for p in &c[1..] {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    Aabb::new(lo, hi)
}

fn union(a: &Aabb, b: &Aabb) -> Aabb {
    Aabb::new(
        Point3::new(a.min.x.min(b.min.x), a.min.y.min(b.min.y), a.min.z.min(b.min.z)),
        Point3::new(a.max.x.max(b.max.x), a.max.y.max(b.max.y), a.max.z.max(b.max.z)),
    )
}

impl Bvh {
    /// Builds the hierarchy (median split on the longest axis of the centroids).
    pub fn build(mesh: &TriangleMesh) -> Self {
        let n = mesh.triangles.len();
        let boxes: Vec<Aabb> = (0..n).map(|t| triangle_bounds(&mesh.corners(t))).collect();
        let centroids: Vec<Point3<f32>> = boxes.iter().map(Aabb::center).collect();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let mut nodes = Vec::with_capacity(2 * n / LEAF_SIZE + 1);
        Self::split(&mut nodes, &mut order, 0, n, &boxes, &centroids);
        Self { nodes, order }
    }

    fn split(
        nodes: &mut Vec<Node>,
        order: &mut [u32],
        lo: usize,
        hi: usize,
        boxes: &[Aabb],
        centroids: &[Point3<f32>],
    ) -> usize {
        let mut bounds = boxes[order[lo] as usize];
        let mut cmin = centroids[order[lo] as usize];
        let mut cmax = cmin;
        for &t in &order[lo..hi] {
            bounds = union(&bounds, &boxes[t as usize]);
            let c = centroids[t as usize];
            for a in 0..3 {
                cmin[a] = cmin[a].min(c[a]);
                cmax[a] = cmax[a].max(c[a]);
            }
        }
        let index = nodes.len();
        nodes.push(Node {
            bounds,
            first: lo as u32,
            count: (hi - lo) as u32,
        });
        let extent = cmax - cmin;
        if hi - lo <= LEAF_SIZE || extent.max() <= 0.0 {
            return index;
        }
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = (lo + hi) / 2;
        order[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
            centroids[*a as usize][axis].total_cmp(&centroids[*b as usize][axis])
        });
        Self::split(nodes, order, lo, mid, boxes, centroids);
        let right = Self::split(nodes, order, mid, hi, boxes, centroids);
        nodes[index].first = right as u32;
        nodes[index].count = 0;
        index
    }

    /// Distance along the unit ray to the first triangle hit within `t_max`.
    pub fn raycast(
        &self,
        mesh: &TriangleMesh,
        origin: &Point3<f32>,
        dir: &Vector3<f32>,
        t_max: f32,
    ) -> Option<f32> {
        self.raycast_triangle(mesh, origin, dir, t_max).map(|(t, _)| t)
    }

    /// [`Bvh::raycast`], also returning the index of the triangle hit.
    pub fn raycast_triangle(
        &self,
        mesh: &TriangleMesh,
        origin: &Point3<f32>,
        dir: &Vector3<f32>,
        t_max: f32,
    ) -> Option<(f32, usize)> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = dir.map(|c| 1.0 / c);
        let mut best = t_max;
        let mut hit = None;
        let mut stack = Vec::with_capacity(64);
        stack.push(0usize);
        while let Some(i) = stack.pop() {
            let node = &self.nodes[i];
            if node.bounds.ray_entry(origin, dir, &inv, best).is_none() {
                continue;
            }
            if node.count > 0 {
                let (a, b) = (node.first as usize, (node.first + node.count) as usize);
                for &t in &self.order[a..b] {
                    if let Some(d) = ray_triangle(origin, dir, &mesh.corners(t as usize)) {
                        if d <= best {
                            best = d;
                            hit = Some(t as usize);
                        }
                    }
                }
            } else {
                stack.push(node.first as usize);
                stack.push(i + 1);
            }
        }
        hit.map(|t| (best, t))
    }

    /// Every distance at which the ray crosses a triangle (for inside tests).
    fn crossings(
        &self,
        mesh: &TriangleMesh,
        origin: &Point3<f32>,
        dir: &Vector3<f32>,
        t_max: f32,
        out: &mut Vec<f32>,
    ) {
        out.clear();
        if self.nodes.is_empty() {
            return;
        }
        let inv = dir.map(|c| 1.0 / c);
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let node = &self.nodes[i];
            if node.bounds.ray_entry(origin, dir, &inv, t_max).is_none() {
                continue;
            }
            if node.count > 0 {
                let (a, b) = (node.first as usize, (node.first + node.count) as usize);
                for &t in &self.order[a..b] {
                    if let Some(d) = ray_triangle(origin, dir, &mesh.corners(t as usize)) {
                        if d <= t_max {
                            out.push(d);
                        }
                    }
                }
            } else {
                stack.push(node.first as usize);
                stack.push(i + 1);
            }
        }
        out.sort_by(f32::total_cmp);
    }

    /// True if some triangle comes closer than `radius` to `p`.
    pub fn within(&self, mesh: &TriangleMesh, p: &Point3<f32>, radius: f32) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let r2 = radius * radius;
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let node = &self.nodes[i];
            if node.bounds.distance_squared_to_point(p) >= r2 {
                continue;
            }
            if node.count > 0 {
                let (a, b) = (node.first as usize, (node.first + node.count) as usize);
                if self.order[a..b]
                    .iter()
                    .any(|&t| (closest_on_triangle(p, &mesh.corners(t as usize)) - p).norm_squared() < r2)
                {
                    return true;
                }
            } else {
                stack.push(node.first as usize);
                stack.push(i + 1);
            }
        }
        false
    }

    /// Calls `f` for every triangle whose box meets `query`.
    fn for_each_near(&self, query: &Aabb, mut f: impl FnMut(usize)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = vec![0usize];
        let overlaps = |b: &Aabb| (0..3).all(|a| b.min[a] <= query.max[a] && b.max[a] >= query.min[a]);
        while let Some(i) = stack.pop() {
            let node = &self.nodes[i];
            if !overlaps(&node.bounds) {
                continue;
            }
            if node.count > 0 {
                let (a, b) = (node.first as usize, (node.first + node.count) as usize);
                for &t in &self.order[a..b] {
                    f(t as usize);
                }
            } else {
                stack.push(node.first as usize);
                stack.push(i + 1);
            }
        }
    }
}

/// Möller–Trumbore: distance along the unit ray to the triangle, if it is hit in front.
fn ray_triangle(o: &Point3<f32>, d: &Vector3<f32>, c: &[Point3<f32>; 3]) -> Option<f32> {
    let e1 = c[1] - c[0];
    let e2 = c[2] - c[0];
    let p = d.cross(&e2);
    let det = e1.dot(&p);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - c[0];
    // A hair of tolerance keeps rays through a shared edge from slipping between triangles.
    const TOL: f32 = 1e-6;
    let u = s.dot(&p) * inv;
    if !(-TOL..=1.0 + TOL).contains(&u) {
        return None;
    }
    let q = s.cross(&e1);
    let v = d.dot(&q) * inv;
    if v < -TOL || u + v > 1.0 + TOL {
        return None;
    }
    let t = e2.dot(&q) * inv;
    (t >= 0.0).then_some(t)
}

/// Closest point of a triangle to `p` (Ericson, Real-Time Collision Detection, 5.1.5).
fn closest_on_triangle(p: &Point3<f32>, c: &[Point3<f32>; 3]) -> Point3<f32> {
    let (a, b, cc) = (c[0], c[1], c[2]);
    let ab = b - a;
    let ac = cc - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - cc;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return cc;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (cc - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Separating-axis test: does the triangle meet the box (centre `c`, half extent `h`)?
fn triangle_box(tri: &[Point3<f32>; 3], c: &Point3<f32>, h: &Vector3<f32>) -> bool {
    let v = tri.map(|p| p - c);
    let e = [v[1] - v[0], v[2] - v[1], v[0] - v[2]];
    // The box's axes.
    for a in 0..3 {
        let (lo, hi) = (
            v[0][a].min(v[1][a]).min(v[2][a]),
            v[0][a].max(v[1][a]).max(v[2][a]),
        );
        if lo > h[a] || hi < -h[a] {
            return false;
        }
    }
    // The triangle's normal.
    let n = e[0].cross(&e[1]);
    let r = h.x * n.x.abs() + h.y * n.y.abs() + h.z * n.z.abs();
    if n.dot(&v[0]).abs() > r {
        return false;
    }
    // Edge × box-axis cross products.
    for edge in &e {
        for a in 0..3 {
            let mut axis_unit = Vector3::zeros();
            axis_unit[a] = 1.0;
            let axis = edge.cross(&axis_unit);
            if axis.norm_squared() < 1e-20 {
                continue;
            }
            let p = v.map(|q| q.dot(&axis));
            let r = h.x * axis.x.abs() + h.y * axis.y.abs() + h.z * axis.z.abs();
            let (lo, hi) = (p[0].min(p[1]).min(p[2]), p[0].max(p[1]).max(p[2]));
            if lo > r || hi < -r {
                return false;
            }
        }
    }
    true
}

/// A placed mesh, its hierarchy and its voxels on the scenario grid.
#[derive(Debug, Clone)]
pub struct MeshObject {
    /// What the scenario file called it (file and placement), for messages and equality.
    pub source: String,
    /// The triangles, map frame.
    pub mesh: TriangleMesh,
    /// Their hierarchy.
    pub bvh: Bvh,
    /// No texture: stereo finds no depth on it.
    pub textureless: bool,
    /// Solid voxels on the scenario grid (x fastest), see [`MeshObject::voxelise`].
    pub solid: Vec<bool>,
    /// The grid `solid` is on: origin, voxel edge, dimensions.
    pub grid: (Point3<f32>, f32, [usize; 3]),
}

impl PartialEq for MeshObject {
    fn eq(&self, other: &Self) -> bool {
        self.source == other.source && self.mesh.triangles.len() == other.mesh.triangles.len()
    }
}

impl MeshObject {
    /// Builds the hierarchy and voxelises the mesh on the grid `(origin, resolution, dims)`.
    pub fn new(
        source: String,
        mesh: TriangleMesh,
        textureless: bool,
        fill: bool,
        grid: (Point3<f32>, f32, [usize; 3]),
    ) -> Self {
        let bvh = Bvh::build(&mesh);
        let solid = Self::voxelise(&mesh, &bvh, fill, grid);
        Self {
            source,
            mesh,
            bvh,
            textureless,
            solid,
            grid,
        }
    }

    /// Solid voxels: the surface's (triangle–box overlap) and, with `fill`, those whose centre
    /// an odd number of surface crossings along +x separates from the outside.
    pub fn voxelise(
        mesh: &TriangleMesh,
        bvh: &Bvh,
        fill: bool,
        grid: (Point3<f32>, f32, [usize; 3]),
    ) -> Vec<bool> {
        let (origin, r, [nx, ny, nz]) = grid;
        let mut solid = vec![false; nx * ny * nz];
        let eps = CELL_EPSILON;
        let h = Vector3::repeat(0.5 * r - eps);
        let index = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
        let cell_of =
            |c: f32, o: f32, n: usize| (((c - o) / r).floor().max(0.0) as usize).min(n.saturating_sub(1));
        for t in 0..mesh.triangles.len() {
            let tri = mesh.corners(t);
            let b = triangle_bounds(&tri);
            if (0..3).any(|a| b.max[a] < origin[a] || b.min[a] > origin[a] + r * [nx, ny, nz][a] as f32) {
                continue;
            }
            let lo = [
                cell_of(b.min.x, origin.x, nx),
                cell_of(b.min.y, origin.y, ny),
                cell_of(b.min.z, origin.z, nz),
            ];
            let hi = [
                cell_of(b.max.x, origin.x, nx),
                cell_of(b.max.y, origin.y, ny),
                cell_of(b.max.z, origin.z, nz),
            ];
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let i = index(x, y, z);
                        if solid[i] {
                            continue;
                        }
                        let c = origin + Vector3::new(x as f32 + 0.5, y as f32 + 0.5, z as f32 + 0.5) * r;
                        if triangle_box(&tri, &c, &h) {
                            solid[i] = true;
                        }
                    }
                }
            }
        }
        if fill {
            let b = mesh.bounds();
            let mut hits = Vec::new();
            // Off the voxel-centre lattice by an irrational-looking amount, so the ray does not
            // run exactly along the edges of grid-aligned meshes.
            let (dy, dz) = (1.37e-3 * r, 2.71e-3 * r);
            for z in 0..nz {
                for y in 0..ny {
                    let oy = origin.y + (y as f32 + 0.5) * r + dy;
                    let oz = origin.z + (z as f32 + 0.5) * r + dz;
                    if oy < b.min.y || oy > b.max.y || oz < b.min.z || oz > b.max.z {
                        continue;
                    }
                    let start = Point3::new(b.min.x.min(origin.x) - 1.0, oy, oz);
                    let length = b.max.x.max(origin.x + r * nx as f32) - start.x + 1.0;
                    // Coincident crossings (touching closed parts) both count.
                    bvh.crossings(mesh, &start, &Vector3::x(), length, &mut hits);
                    for x in 0..nx {
                        let cx = origin.x + (x as f32 + 0.5) * r - start.x;
                        let crossed = hits.partition_point(|&t| t < cx);
                        if crossed % 2 == 1 {
                            solid[index(x, y, z)] = true;
                        }
                    }
                }
            }
        }
        solid
    }

    /// True if the grid cell containing `p` is solid.
    pub fn solid_at(&self, p: &Point3<f32>) -> bool {
        let (origin, r, [nx, ny, nz]) = self.grid;
        let g = (p - origin) / r;
        if g.iter().any(|c| !c.is_finite() || *c < 0.0) {
            return false;
        }
        let (x, y, z) = (g.x as usize, g.y as usize, g.z as usize);
        x < nx && y < ny && z < nz && self.solid[x + nx * (y + ny * z)]
    }

    /// Triangles whose boxes meet `query` (for tests and tools).
    pub fn triangles_near(&self, query: &Aabb) -> usize {
        let mut n = 0;
        self.bvh.for_each_near(query, |_| n += 1);
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An axis-aligned cuboid as OBJ text (8 vertices, 6 quads).
    fn cuboid_obj(lo: [f32; 3], hi: [f32; 3], first_vertex: usize) -> String {
        let mut s = String::new();
        for k in 0..8 {
            let p = [0, 1, 2].map(|a| if k & (1 << a) != 0 { hi[a] } else { lo[a] });
            s.push_str(&format!("v {} {} {}\n", p[0], p[1], p[2]));
        }
        let f = |a: usize, b: usize, c: usize, d: usize| {
            format!(
                "f {} {} {} {}\n",
                a + first_vertex,
                b + first_vertex,
                c + first_vertex,
                d + first_vertex
            )
        };
        // Vertex k+1 has bits x = 1, y = 2, z = 4.
        s += &f(1, 3, 4, 2); // z = lo
        s += &f(5, 6, 8, 7); // z = hi
        s += &f(1, 2, 6, 5); // y = lo
        s += &f(3, 7, 8, 4); // y = hi
        s += &f(1, 5, 7, 3); // x = lo
        s += &f(2, 4, 8, 6); // x = hi
        s
    }

    fn grid(n: usize) -> (Point3<f32>, f32, [usize; 3]) {
        (Point3::origin(), 0.1, [n, n, n])
    }

    fn solid_set(obj: &MeshObject) -> Vec<[usize; 3]> {
        let (_, _, [nx, ny, _]) = obj.grid;
        (0..obj.solid.len())
            .filter(|&i| obj.solid[i])
            .map(|i| [i % nx, (i / nx) % ny, i / (nx * ny)])
            .collect()
    }

    #[test]
    fn obj_cube_voxelises_to_exactly_its_voxels() {
        let mesh = TriangleMesh::from_obj(&cuboid_obj([0.2, 0.2, 0.2], [0.8, 0.8, 0.8], 0)).unwrap();
        assert_eq!((mesh.vertices.len(), mesh.triangles.len()), (8, 12));
        let obj = MeshObject::new("cube".into(), mesh.clone(), false, true, grid(10));
        let expected: Vec<[usize; 3]> = (2..8)
            .flat_map(|z| (2..8).flat_map(move |y| (2..8).map(move |x| [x, y, z])))
            .collect();
        assert_eq!(solid_set(&obj), expected);
        // Faces on voxel boundaries claim no voxel: unfilled, the grid-aligned cube is empty.
        let hollow = MeshObject::new("cube".into(), mesh, false, false, grid(10));
        assert!(solid_set(&hollow).is_empty());
        // Faces through voxel middles: the shell is the 6³ − 4³ voxels they pass through.
        let off = TriangleMesh::from_obj(&cuboid_obj([0.25; 3], [0.75; 3], 0)).unwrap();
        let shell = MeshObject::new("cube".into(), off.clone(), false, false, grid(10));
        assert_eq!(solid_set(&shell).len(), 216 - 64);
        let filled = MeshObject::new("cube".into(), off, false, true, grid(10));
        assert_eq!(solid_set(&filled).len(), 216);
    }

    #[test]
    fn obj_room_of_walls_keeps_its_inside_free() {
        // A 1 m room: six 0.1 m cuboid slabs, one OBJ.
        let walls = [
            ([0.0, 0.0, 0.0], [1.0, 1.0, 0.1]),
            ([0.0, 0.0, 0.9], [1.0, 1.0, 1.0]),
            ([0.0, 0.0, 0.1], [0.1, 1.0, 0.9]),
            ([0.9, 0.0, 0.1], [1.0, 1.0, 0.9]),
            ([0.1, 0.0, 0.1], [0.9, 0.1, 0.9]),
            ([0.1, 0.9, 0.1], [0.9, 1.0, 0.9]),
        ];
        let mut text = String::from("# room\no walls\n");
        for (k, (lo, hi)) in walls.iter().enumerate() {
            text += &cuboid_obj(*lo, *hi, 8 * k);
        }
        let mesh = TriangleMesh::from_obj(&text).unwrap();
        let obj = MeshObject::new("room".into(), mesh, false, true, grid(10));
        let solid = solid_set(&obj);
        assert_eq!(solid.len(), 1000 - 512, "the walls, and not the 8³ inside");
        assert!(solid.iter().all(|v| v.iter().any(|&c| c == 0 || c == 9)));
    }

    #[test]
    fn rays_hit_the_surface_exactly_and_spheres_collide() {
        let mut mesh = TriangleMesh::from_obj(&cuboid_obj([0.0; 3], [1.0; 3], 0)).unwrap();
        mesh.transform([2.0, 1.0, 1.0], 0.0, [3.0, -0.5, -0.5]);
        let bvh = Bvh::build(&mesh);
        let t = bvh
            .raycast(&mesh, &Point3::origin(), &Vector3::x(), 60.0)
            .unwrap();
        assert!((t - 3.0).abs() < 1e-6, "{t}");
        let d = Vector3::new(1.0, 0.1, 0.05).normalize();
        let t = bvh.raycast(&mesh, &Point3::origin(), &d, 60.0).unwrap();
        assert!((t * d.x - 3.0).abs() < 1e-5, "{t}");
        assert!(bvh
            .raycast(&mesh, &Point3::origin(), &-Vector3::x(), 60.0)
            .is_none());
        assert!(bvh.within(&mesh, &Point3::new(2.8, 0.0, 0.0), 0.25));
        assert!(!bvh.within(&mesh, &Point3::new(2.7, 0.0, 0.0), 0.25));
    }

    #[test]
    fn stl_binary_and_ascii_agree_and_bad_input_is_an_error() {
        let tri = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let mut bin = vec![0u8; 80];
        bin.extend_from_slice(&1u32.to_le_bytes());
        bin.extend_from_slice(&[0u8; 12]);
        for v in tri {
            for c in v {
                bin.extend_from_slice(&c.to_le_bytes());
            }
        }
        bin.extend_from_slice(&[0, 0]);
        let a = TriangleMesh::from_stl(&bin).unwrap();
        let ascii = "solid t\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n   vertex 0 1 0\n  endloop\n endfacet\nendsolid t\n";
        let b = TriangleMesh::from_stl(ascii.as_bytes()).unwrap();
        assert_eq!(a, b);
        assert!(TriangleMesh::from_obj("v 0 0 0\nf 1 2 3\n")
            .unwrap_err()
            .0
            .contains("line 2"));
        assert!(TriangleMesh::from_obj("v 0 0 x\n").is_err());
        assert!(TriangleMesh::from_stl(b"solid empty\nendsolid\n").is_err());
    }

    fn fixture(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenarios/fixtures/meshes")
            .join(name)
    }

    fn corners_of(mesh: &TriangleMesh, t: usize) -> [[f32; 3]; 3] {
        mesh.corners(t).map(|p| [p.x, p.y, p.z])
    }

    /// A binary STL: `header` (padded to 80 bytes), then the triangles, normals zero.
    fn binary_stl(header: &[u8], triangles: &[[[f32; 3]; 3]]) -> Vec<u8> {
        let mut bin = header.to_vec();
        bin.resize(80, b' ');
        bin.extend_from_slice(&(triangles.len() as u32).to_le_bytes());
        for t in triangles {
            bin.extend_from_slice(&[0u8; 12]);
            for c in t.iter().flatten() {
                bin.extend_from_slice(&c.to_le_bytes());
            }
            bin.extend_from_slice(&[0, 0]);
        }
        bin
    }

    /// The repository's mesh fixtures (`mesh-rooms.toml`): triangle counts, bounds and exact
    /// corners, as the hand-written readers gave them (checked against the files, not copied).
    #[test]
    fn fixtures_give_the_same_triangles() {
        let obj = TriangleMesh::load(&fixture("two-rooms.obj")).unwrap();
        assert_eq!((obj.vertices.len(), obj.triangles.len()), (80, 120));
        let b = obj.bounds();
        assert_eq!(
            (b.min, b.max),
            (Point3::new(0.0, 0.0, 0.0), Point3::new(5.0, 3.0, 2.0))
        );
        // Quads become fans (v0, v1, v2), (v0, v2, v3).
        assert_eq!(
            corners_of(&obj, 0),
            [[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [5.0, 3.0, 0.0]]
        );
        assert_eq!(
            corners_of(&obj, 1),
            [[0.0, 0.0, 0.0], [5.0, 3.0, 0.0], [5.0, 0.0, 0.0]]
        );
        assert_eq!(
            corners_of(&obj, 119),
            [[4.2, 1.1, 0.1], [4.2, 1.9, 0.8], [4.2, 1.1, 0.8]]
        );

        let stl = TriangleMesh::load(&fixture("table-cm.stl")).unwrap();
        assert_eq!((stl.vertices.len(), stl.triangles.len()), (36, 12));
        let b = stl.bounds();
        assert_eq!(
            (b.min, b.max),
            (Point3::new(360.0, 110.0, 10.0), Point3::new(420.0, 190.0, 80.0))
        );
        // Corners are not shared: triangle t is vertices 3t, 3t + 1, 3t + 2, in file order.
        assert!(stl
            .triangles
            .iter()
            .enumerate()
            .all(|(t, v)| *v == [0, 1, 2].map(|k| (3 * t + k) as u32)));
        assert_eq!(
            corners_of(&stl, 0),
            [[360.0, 110.0, 10.0], [360.0, 190.0, 10.0], [420.0, 190.0, 10.0]]
        );
        assert_eq!(
            corners_of(&stl, 1),
            [[360.0, 110.0, 10.0], [420.0, 190.0, 10.0], [420.0, 110.0, 10.0]]
        );
        assert_eq!(
            corners_of(&stl, 11),
            [[420.0, 110.0, 10.0], [420.0, 190.0, 80.0], [420.0, 110.0, 80.0]]
        );
    }

    /// Binary is told from ASCII by size: a binary header that starts with `solid` (as some CAD
    /// exporters write it) is still binary, even when the triangle count's low byte is a line
    /// feed (10 triangles) so that the header reads as a text line; a file one byte longer than
    /// its header announces is not binary, and not text either.
    #[test]
    fn binary_stl_is_told_by_its_size_not_its_header() {
        let tris: Vec<[[f32; 3]; 3]> = (0..10)
            .map(|k| [[0.0, 0.0, k as f32], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
            .collect();
        let bin = binary_stl(b"solid part, exported as binary", &tris);
        let mesh = TriangleMesh::from_stl(&bin).unwrap();
        assert_eq!(mesh.triangles.len(), 10);
        for (t, tri) in tris.iter().enumerate() {
            assert_eq!(corners_of(&mesh, t), *tri);
        }
        assert_eq!(
            TriangleMesh::from_stl(&binary_stl(b"binary", &[])).unwrap_err().0,
            "binary STL with no facets"
        );
        let mut long = binary_stl(b"binary", &tris);
        long.push(0);
        assert!(TriangleMesh::from_stl(&long)
            .unwrap_err()
            .0
            .contains("neither binary"));
    }

    /// ASCII STL: every `vertex` line counts, three to a facet, whatever surrounds them: a
    /// nameless `solid`, several solids in one file, a missing `endsolid`.
    #[test]
    fn ascii_stl_reads_every_facet() {
        let facet = |z: f32| {
            format!(
                "facet normal 0 0 1\nouter loop\nvertex 0 0 {z}\nvertex 1 0 {z}\nvertex 0 1 {z}\nendloop\nendfacet\n"
            )
        };
        let nameless = format!("solid\n{}endsolid\n", facet(0.0));
        assert_eq!(
            TriangleMesh::from_stl(nameless.as_bytes())
                .unwrap()
                .triangles
                .len(),
            1
        );
        let two = format!(
            "solid a\n{}endsolid a\nsolid b\n{}endsolid b\n",
            facet(0.0),
            facet(5.0)
        );
        let mesh = TriangleMesh::from_stl(two.as_bytes()).unwrap();
        assert_eq!(mesh.triangles.len(), 2);
        assert_eq!(corners_of(&mesh, 1)[0], [0.0, 0.0, 5.0]);
        let open = format!("solid t\n{}", facet(1.0));
        assert_eq!(
            TriangleMesh::from_stl(open.as_bytes()).unwrap().triangles.len(),
            1
        );
    }

    /// OBJ: polylines (`l`) are not surfaces, a face needs three corners, coordinates must be
    /// finite, and errors name the line; texture and normal indices are not checked.
    #[test]
    fn obj_reads_faces_only_and_names_the_bad_line() {
        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        let with_line = format!("{tri}v 0 0 1\nf 1 2 3\nl 1 2 4\n");
        assert_eq!(TriangleMesh::from_obj(&with_line).unwrap().triangles.len(), 1);
        let err = TriangleMesh::from_obj(&format!("{tri}f 1 2 3\nf 1 2\n")).unwrap_err();
        assert_eq!(err.0, "line 5: a face needs 3 vertices");
        let err = TriangleMesh::from_obj("v 0 0 0\nv inf 0 0\n").unwrap_err();
        assert_eq!(err.0, "line 2: coordinate not finite");
        let err = TriangleMesh::from_obj(&format!("{tri}f 1 2 4\n")).unwrap_err();
        assert_eq!(err.0, "line 4: face index 4 refers to no vertex (3 so far)");
        // `v x y z w`: w is ignored (not divided by); `vt`/`vn` indices are not looked up.
        let mesh = TriangleMesh::from_obj("v 2 2 2 2\nv 1 0 0\nv 0 1 0\nvt 0\nf 1/7 2/7 3/7\n").unwrap();
        assert_eq!(corners_of(&mesh, 0)[0], [2.0, 2.0, 2.0]);
        // A material library that is not there does not matter.
        let mtl = format!("mtllib missing.mtl\n{tri}usemtl red\nf -3 -2 -1\n");
        assert_eq!(TriangleMesh::from_obj(&mtl).unwrap().triangles.len(), 1);
    }
}
