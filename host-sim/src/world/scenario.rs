//! Scenarios: a world, the voxel size to map it with and where the vehicle starts, read from
//! TOML and validated once, here, into a [`Scenario`] that cannot be wrong afterwards.
//!
//! # File format
//!
//! ```toml
//! name = "apartment"
//! resolution = 0.1            # metres per voxel, in (0.01, 1.0]
//!
//! [bounds]                    # the mapped region; each extent a whole number of voxels
//! min = [0.0, 0.0, 0.0]
//! max = [6.0, 8.0, 2.5]
//!
//! [start]
//! position = [1.0, 1.0, 1.2]  # metres, map frame, z up; ≥ 0.3 m from every box and the bounds
//! yaw_deg = 0.0               # 0 = looking along +x, counter-clockwise positive
//!
//! [[box]]                     # a solid axis-aligned box; repeat for every obstacle
//! min = [0.0, 0.0, 0.0]
//! max = [6.0, 8.0, 0.1]
//! label = "floor slab"        # optional, for people reading the file
//! textureless = false         # optional: stereo finds no depth on it (`explore --textureless`)
//!
//! [[mesh]]                    # a triangle mesh: Wavefront OBJ or STL (binary or ASCII)
//! file = "models/chair.obj"   # relative to this file's directory
//! scale = 0.01                # optional: a number or [sx, sy, sz] (e.g. centimetres → metres)
//! rotate_z_deg = 90.0         # optional: about the map's z axis, after scaling
//! translate = [2.0, 3.0, 0.1] # optional: after rotating
//! fill = true                 # optional (default true): interiors of closed surfaces are solid
//! textureless = false         # optional
//! ```
//!
//! Meshes are ray cast exactly by the camera (a BVH over the triangles) and voxelised on the
//! scenario grid for coverage: surface voxels and, with `fill`, the inside of closed surfaces
//! (see [`crate::world::mesh`]).
//!
//! Unknown keys are errors. Every error is one line naming the file and the place: the TOML
//! line and column for syntax and type errors (`office.toml:12:1: unknown field ...`), the item
//! for invalid values (`apartment.toml: box[3]: min.z 2.0 >= max.z 1.0 (line 40)`).
//!
//! # Built-in scenarios
//!
//! [`builtin_names`] lists worlds embedded in the binary (their sources are in
//! `host-sim/scenarios/`). They are drawn so that a level depth camera on a vehicle with 0.2 m
//! clearance can see all of their free space: coordinates on the 0.1 m grid, closed shells,
//! doors ≥ 0.9 m, and no gap narrower than 0.7 m between obstacles.

use std::fmt;
use std::path::Path;

use nalgebra::Point3;
use serde::Deserialize;
use toml::Spanned;

use crate::world::{Aabb, World};

/// Voxel size limits, metres: `MIN_RESOLUTION < resolution <= MAX_RESOLUTION`.
pub const MIN_RESOLUTION: f32 = 0.01;
/// See [`MIN_RESOLUTION`].
pub const MAX_RESOLUTION: f32 = 1.0;
/// Largest grid dimension along any axis, voxels.
pub const MAX_VOXELS_PER_AXIS: usize = 512;
/// Largest total grid size, voxels.
pub const MAX_VOXELS: usize = 16 * 1024 * 1024;
/// Minimum clearance between the start position and every box or the bounds, metres.
pub const START_CLEARANCE: f32 = 0.3;
/// How far (in voxels) a bounds extent may be from a whole number of voxels.
const WHOLE_VOXEL_TOLERANCE: f32 = 1e-3;

const BUILTIN_NAMES: [&str; 10] = [
    "apartment",
    "office",
    "two-level",
    "s1",
    "s2",
    "kitchen",
    "s4",
    "apartment-thesis",
    "garage",
    "pil-small",
];
const BUILTIN_SOURCES: [&str; 10] = [
    include_str!("../../scenarios/apartment.toml"),
    include_str!("../../scenarios/office.toml"),
    include_str!("../../scenarios/two-level.toml"),
    include_str!("../../scenarios/s1.toml"),
    include_str!("../../scenarios/s2.toml"),
    include_str!("../../scenarios/kitchen.toml"),
    include_str!("../../scenarios/s4.toml"),
    include_str!("../../scenarios/apartment-thesis.toml"),
    include_str!("../../scenarios/garage.toml"),
    include_str!("../../scenarios/pil-small.toml"),
];

/// The six scenarios of the seed thesis's comparison (Shade 2011, §6.5), in its order.
pub const THESIS_SCENARIOS: [&str; 6] = ["s1", "s2", "kitchen", "s4", "apartment-thesis", "garage"];

/// Names of the scenarios built into the simulator.
pub fn builtin_names() -> &'static [&'static str] {
    &BUILTIN_NAMES
}

/// A validated scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    /// Ground truth the simulator renders and measures against.
    pub world: World,
    /// Voxel edge length, metres.
    pub resolution: f32,
    /// Vehicle start position, map frame.
    pub start_position: Point3<f32>,
    /// Vehicle start heading, radians about map z (0 = +x, counter-clockwise positive).
    pub start_yaw: f32,
}

/// Why a scenario could not be loaded. Displays as one line that names the file (`origin`)
/// and the place of the problem.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ScenarioError {
    /// The file could not be read, or the name is neither a built-in nor a file.
    Read {
        /// File name or path as given.
        origin: String,
        /// What went wrong.
        message: String,
    },
    /// The text is not valid TOML or does not have the scenario's shape.
    Parse {
        /// File name or path.
        origin: String,
        /// 1-based line of the offending text.
        line: usize,
        /// 1-based column (in characters) of the offending text.
        column: usize,
        /// The parser's message.
        message: String,
    },
    /// The file parsed, but a value is out of range or inconsistent.
    Invalid {
        /// File name or path.
        origin: String,
        /// Which item is wrong, e.g. `box[3]`, `bounds`, `start`.
        location: String,
        /// 1-based line of the item in the file, when known.
        line: Option<usize>,
        /// What is wrong with it.
        message: String,
    },
}

impl fmt::Display for ScenarioError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read { origin, message } => write!(f, "{origin}: {}", one_line(message)),
            Self::Parse {
                origin,
                line,
                column,
                message,
            } => {
                write!(f, "{origin}:{line}:{column}: {}", one_line(message))
            }
            Self::Invalid {
                origin,
                location,
                line,
                message,
            } => {
                write!(f, "{origin}: {location}: {}", one_line(message))?;
                match line {
                    Some(line) => write!(f, " (line {line})"),
                    None => Ok(()),
                }
            }
        }
    }
}

impl std::error::Error for ScenarioError {}

fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

impl Scenario {
    /// Parses and validates scenario text; `origin` names it in errors (a file name or path).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Scenario, ScenarioError> {
        let file: ScenarioFile = toml::from_str(text).map_err(|e| {
            let (line, column) = e.span().map_or((1, 1), |span| line_column(text, span.start));
            ScenarioError::Parse {
                origin: origin.to_owned(),
                line,
                column,
                message: e.message().to_owned(),
            }
        })?;
        file.validate(text, origin)
    }

    /// Reads and validates a scenario file.
    pub fn load(path: impl AsRef<Path>) -> Result<Scenario, ScenarioError> {
        let path = path.as_ref();
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ScenarioError::Read {
            origin: origin.clone(),
            message: format!("cannot read: {e}"),
        })?;
        Self::from_toml_str(&text, &origin)
    }

    /// The built-in scenario called `name` (see [`builtin_names`]).
    pub fn builtin(name: &str) -> Option<Scenario> {
        let index = BUILTIN_NAMES.iter().position(|&n| n == name)?;
        let origin = format!("{name}.toml");
        // Built-ins are validated by the unit tests; failing here is a bug in this crate.
        Some(Self::from_toml_str(BUILTIN_SOURCES[index], &origin).unwrap_or_else(|e| panic!("{e}")))
    }

    /// A built-in scenario by name, or else a scenario file at path `s`.
    pub fn by_name_or_path(s: &str) -> Result<Scenario, ScenarioError> {
        if let Some(scenario) = Self::builtin(s) {
            return Ok(scenario);
        }
        let path = Path::new(s);
        if path.exists() {
            return Self::load(path);
        }
        Err(ScenarioError::Read {
            origin: s.to_owned(),
            message: format!(
                "neither a built-in scenario ({}) nor an existing file",
                BUILTIN_NAMES.join(", ")
            ),
        })
    }

    /// Map size in voxels along x, y, z: `round(extent / resolution)`.
    pub fn grid_dims(&self) -> [usize; 3] {
        grid_dims(&self.world.bounds, self.resolution)
    }

    /// Scenario name (the world's).
    pub fn name(&self) -> &str {
        &self.world.name
    }

    /// The same scenario with a random start pose drawn from `seed`: a voxel centre at least
    /// [`START_CLEARANCE`] from every obstacle and the bounds, in the space such positions
    /// connect (through face neighbours) to the scenario's own start, drawn uniformly; the yaw
    /// uniform in [−180°, 180°). The same seed always gives the same pose, so every planner of a
    /// batch starts where the others did. If no such voxel exists the scenario is returned as is.
    pub fn with_random_start(&self, seed: u64) -> Scenario {
        use rand::{Rng, SeedableRng};
        let [nx, ny, nz] = self.grid_dims();
        let r = self.resolution;
        let origin = self.world.bounds.min;
        let centre = |x: usize, y: usize, z: usize| {
            origin + nalgebra::Vector3::new(x as f32 + 0.5, y as f32 + 0.5, z as f32 + 0.5) * r
        };
        let index = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
        let clear: Vec<bool> = (0..nx * ny * nz)
            .map(|i| {
                let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
                !self.world.sphere_collides(&centre(x, y, z), START_CLEARANCE)
            })
            .collect();
        let g = (self.start_position - origin) / r;
        let start = [g.x, g.y, g.z].map(|c| c.floor().max(0.0) as usize);
        let (sx, sy, sz) = (start[0].min(nx - 1), start[1].min(ny - 1), start[2].min(nz - 1));
        let mut reached = vec![false; clear.len()];
        let mut stack = Vec::new();
        if clear[index(sx, sy, sz)] {
            reached[index(sx, sy, sz)] = true;
            stack.push((sx, sy, sz));
        }
        let mut candidates = Vec::new();
        while let Some((x, y, z)) = stack.pop() {
            candidates.push((x, y, z));
            let mut visit = |x: usize, y: usize, z: usize| {
                let i = index(x, y, z);
                if clear[i] && !reached[i] {
                    reached[i] = true;
                    stack.push((x, y, z));
                }
            };
            if x > 0 {
                visit(x - 1, y, z);
            }
            if x + 1 < nx {
                visit(x + 1, y, z);
            }
            if y > 0 {
                visit(x, y - 1, z);
            }
            if y + 1 < ny {
                visit(x, y + 1, z);
            }
            if z > 0 {
                visit(x, y, z - 1);
            }
            if z + 1 < nz {
                visit(x, y, z + 1);
            }
        }
        if candidates.is_empty() {
            return self.clone();
        }
        // Sorted, so the draw does not depend on the fill order.
        candidates.sort_unstable_by_key(|&(x, y, z)| index(x, y, z));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let (x, y, z) = candidates[rng.random_range(0..candidates.len())];
        let yaw_deg: f32 = rng.random_range(-180.0..180.0);
        Scenario {
            start_position: centre(x, y, z),
            start_yaw: yaw_deg.to_radians(),
            ..self.clone()
        }
    }
}

fn grid_dims(bounds: &Aabb, resolution: f32) -> [usize; 3] {
    let e = bounds.extent();
    [e.x, e.y, e.z].map(|x| (x / resolution).round() as usize)
}

/// 1-based line and character column of byte `offset` in `text`.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, before[line_start..].chars().count() + 1)
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioFile {
    name: String,
    resolution: f32,
    bounds: BoundsFile,
    start: StartFile,
    #[serde(rename = "box", default)]
    boxes: Vec<Spanned<BoxFile>>,
    #[serde(rename = "mesh", default)]
    meshes: Vec<Spanned<MeshFile>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MeshFile {
    file: String,
    #[serde(default)]
    scale: Option<ScaleFile>,
    #[serde(default)]
    rotate_z_deg: f32,
    #[serde(default)]
    translate: [f32; 3],
    #[serde(default = "default_true")]
    fill: bool,
    #[serde(default)]
    textureless: bool,
    #[allow(dead_code)]
    label: Option<String>,
}

fn default_true() -> bool {
    true
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum ScaleFile {
    Uniform(f32),
    PerAxis([f32; 3]),
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BoundsFile {
    min: [f32; 3],
    max: [f32; 3],
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct StartFile {
    position: [f32; 3],
    yaw_deg: f32,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxFile {
    min: [f32; 3],
    max: [f32; 3],
    // Read so that the key is allowed; it exists for people reading the file.
    #[allow(dead_code)]
    label: Option<String>,
    /// No texture: a stereo camera finds no depth on it (`explore --textureless`).
    #[serde(default)]
    textureless: bool,
}

const AXES: [char; 3] = ['x', 'y', 'z'];

/// Why a box is malformed: a non-finite coordinate or an empty extent.
fn box_problem(min: &[f32; 3], max: &[f32; 3]) -> Option<String> {
    for i in 0..3 {
        let axis = AXES[i];
        if !min[i].is_finite() {
            return Some(format!("min.{axis} is {:?}", min[i]));
        }
        if !max[i].is_finite() {
            return Some(format!("max.{axis} is {:?}", max[i]));
        }
        if min[i] >= max[i] {
            return Some(format!("min.{axis} {:?} >= max.{axis} {:?}", min[i], max[i]));
        }
    }
    None
}

impl ScenarioFile {
    fn validate(self, text: &str, origin: &str) -> Result<Scenario, ScenarioError> {
        let invalid = |location: &str, line: Option<usize>, message: String| ScenarioError::Invalid {
            origin: origin.to_owned(),
            location: location.to_owned(),
            line,
            message,
        };

        if self.name.trim().is_empty() {
            return Err(invalid("name", None, "is empty".into()));
        }
        let res = self.resolution;
        if !(res.is_finite() && res > MIN_RESOLUTION && res <= MAX_RESOLUTION) {
            return Err(invalid(
                "resolution",
                None,
                format!("{res:?} m is outside ({MIN_RESOLUTION:?}, {MAX_RESOLUTION:?}]"),
            ));
        }

        if let Some(problem) = box_problem(&self.bounds.min, &self.bounds.max) {
            return Err(invalid("bounds", None, problem));
        }
        let bounds = Aabb::from_arrays(self.bounds.min, self.bounds.max);
        let extent = bounds.extent();
        for i in 0..3 {
            let voxels = extent[i] / res;
            if (voxels - voxels.round()).abs() > WHOLE_VOXEL_TOLERANCE {
                return Err(invalid(
                    "bounds",
                    None,
                    format!(
                        "extent.{} {:?} m is not a whole number of {res:?} m voxels",
                        AXES[i], extent[i]
                    ),
                ));
            }
        }
        let dims = grid_dims(&bounds, res);
        if let Some(i) = (0..3).find(|&i| dims[i] > MAX_VOXELS_PER_AXIS) {
            return Err(invalid(
                "bounds",
                None,
                format!(
                    "{} voxels along {} (at most {MAX_VOXELS_PER_AXIS})",
                    dims[i], AXES[i]
                ),
            ));
        }
        let total: usize = dims.iter().product();
        if total > MAX_VOXELS {
            return Err(invalid(
                "bounds",
                None,
                format!(
                    "{}×{}×{} = {total} voxels (at most {MAX_VOXELS})",
                    dims[0], dims[1], dims[2]
                ),
            ));
        }

        let mut boxes = Vec::with_capacity(self.boxes.len());
        let textureless: Vec<bool> = self.boxes.iter().map(|b| b.get_ref().textureless).collect();
        for (index, spanned) in self.boxes.iter().enumerate() {
            let b = spanned.get_ref();
            if let Some(problem) = box_problem(&b.min, &b.max) {
                let line = line_column(text, spanned.span().start).0;
                return Err(invalid(&format!("box[{index}]"), Some(line), problem));
            }
            boxes.push(Aabb::from_arrays(b.min, b.max));
        }
        let mut world = World::new(self.name, bounds, boxes);
        if textureless.iter().any(|&t| t) {
            world.textureless = textureless;
        }
        let base = Path::new(origin).parent().filter(|p| p.exists());
        for (index, spanned) in self.meshes.iter().enumerate() {
            let m = spanned.get_ref();
            let line = Some(line_column(text, spanned.span().start).0);
            let location = format!("mesh[{index}]");
            let scale = match m.scale {
                None => [1.0; 3],
                Some(ScaleFile::Uniform(s)) => [s; 3],
                Some(ScaleFile::PerAxis(s)) => s,
            };
            if !scale.iter().all(|s| s.is_finite() && *s > 0.0)
                || !m.translate.iter().all(|t| t.is_finite())
                || !m.rotate_z_deg.is_finite()
            {
                return Err(invalid(
                    &location,
                    line,
                    "scale must be positive, translate and rotate_z_deg finite".into(),
                ));
            }
            let path = match base {
                Some(b) if Path::new(&m.file).is_relative() => b.join(&m.file),
                _ => Path::new(&m.file).to_path_buf(),
            };
            let mut mesh = crate::world::mesh::TriangleMesh::load(&path)
                .map_err(|e| invalid(&location, line, format!("{}: {e}", path.display())))?;
            mesh.transform(scale, m.rotate_z_deg.to_radians(), m.translate);
            let source = format!(
                "{} scale {scale:?} rotate_z {} translate {:?}",
                path.display(),
                m.rotate_z_deg,
                m.translate
            );
            world
                .meshes
                .push(std::sync::Arc::new(crate::world::mesh::MeshObject::new(
                    source,
                    mesh,
                    m.textureless,
                    m.fill,
                    (bounds.min, res, dims),
                )));
        }

        let p = self.start.position;
        if let Some(i) = (0..3).find(|&i| !p[i].is_finite()) {
            return Err(invalid(
                "start",
                None,
                format!("position.{} is {:?}", AXES[i], p[i]),
            ));
        }
        if !self.start.yaw_deg.is_finite() {
            return Err(invalid(
                "start",
                None,
                format!("yaw_deg is {:?}", self.start.yaw_deg),
            ));
        }
        let start = Point3::from(p);
        let p_text = format!("position [{:?}, {:?}, {:?}]", p[0], p[1], p[2]);
        if !world.sphere_inside_bounds(&start, START_CLEARANCE) {
            return Err(invalid(
                "start",
                None,
                format!("{p_text} is not inside the bounds with {START_CLEARANCE:?} m to spare"),
            ));
        }
        if let Some(index) = world.first_mesh_within(&start, START_CLEARANCE) {
            return Err(invalid(
                "start",
                None,
                format!("{p_text} is within {START_CLEARANCE:?} m of mesh[{index}]"),
            ));
        }
        if let Some(index) = world.first_box_within(&start, START_CLEARANCE) {
            let line = line_column(text, self.boxes[index].span().start).0;
            return Err(invalid(
                "start",
                None,
                format!("{p_text} is within {START_CLEARANCE:?} m of box[{index}] (line {line})"),
            ));
        }

        Ok(Scenario {
            world,
            resolution: res,
            start_position: start,
            start_yaw: self.start.yaw_deg.to_radians(),
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    const MINIMAL: &str = r#"
name = "minimal"
resolution = 0.1
[bounds]
min = [0.0, 0.0, 0.0]
max = [4.0, 3.0, 2.5]
[start]
position = [2.0, 1.5, 1.2]
yaw_deg = 90
[[box]]
min = [0.0, 0.0, 0.0]
max = [4, 3, 0.1]
"#;

    fn fixture(name: &str) -> String {
        format!("{}/scenarios/fixtures/{name}", env!("CARGO_MANIFEST_DIR"))
    }

    fn error_of(text: &str) -> String {
        Scenario::from_toml_str(text, "t.toml").unwrap_err().to_string()
    }

    #[test]
    fn minimal_scenario_parses() {
        let s = Scenario::from_toml_str(MINIMAL, "minimal.toml").unwrap();
        assert_eq!(s.name(), "minimal");
        assert_eq!(s.grid_dims(), [40, 30, 25]);
        assert_eq!(s.world.boxes.len(), 1);
        assert!((s.start_yaw - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(s.start_position, Point3::new(2.0, 1.5, 1.2));
    }

    #[test]
    fn random_starts_are_clear_reproducible_and_spread() {
        let s = Scenario::builtin("apartment-thesis").unwrap();
        let a = s.with_random_start(7);
        assert_eq!(a, s.with_random_start(7));
        let starts: Vec<Scenario> = (1..=20).map(|seed| s.with_random_start(seed)).collect();
        for t in &starts {
            assert!(!t.world.sphere_collides(&t.start_position, START_CLEARANCE));
            assert!((-std::f32::consts::PI..std::f32::consts::PI).contains(&t.start_yaw));
            assert_eq!(t.world, s.world);
        }
        // Twenty draws over the whole apartment land in more than one room.
        let rooms: std::collections::BTreeSet<(bool, bool)> = starts
            .iter()
            .map(|t| (t.start_position.x > 3.6, t.start_position.y > 4.5))
            .collect();
        assert!(rooms.len() >= 3, "{rooms:?}");
    }

    #[test]
    fn every_builtin_loads_and_validates() {
        for name in builtin_names() {
            let s = Scenario::builtin(name).unwrap();
            assert_eq!(s.name(), *name);
            assert_eq!(Scenario::by_name_or_path(name).unwrap(), s);
        }
        assert!(Scenario::builtin("castle").is_none());
    }

    #[test]
    fn inverted_box_fixture_names_file_box_and_line() {
        let path = fixture("inverted-box.toml");
        let err = Scenario::by_name_or_path(&path).unwrap_err().to_string();
        assert_eq!(err, format!("{path}: box[1]: min.z 2.0 >= max.z 1.0 (line 18)"));
    }

    #[test]
    fn unknown_field_fixture_names_line_and_column() {
        let path = fixture("unknown-field.toml");
        let err = Scenario::load(&path).unwrap_err();
        assert!(
            matches!(
                err,
                ScenarioError::Parse {
                    line: 16,
                    column: 1,
                    ..
                }
            ),
            "{err:?}"
        );
        let text = err.to_string();
        assert!(
            text.starts_with(&format!("{path}:16:1: unknown field `colour`")),
            "{text}"
        );
        assert!(!text.contains('\n'));
    }

    #[test]
    fn missing_file_and_unknown_name() {
        let err = Scenario::by_name_or_path("no-such-world")
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("no-such-world: neither a built-in scenario (apartment"),
            "{err}"
        );
        let err = Scenario::load("/nonexistent/x.toml").unwrap_err().to_string();
        assert!(err.starts_with("/nonexistent/x.toml: cannot read:"), "{err}");
    }

    #[test]
    fn syntax_error_has_line_and_column() {
        let err = error_of("name = \"x\"\nresolution = = 0.1\n");
        assert!(err.starts_with("t.toml:2:"), "{err}");
        assert!(!err.contains('\n'));
    }

    #[test]
    fn validation_errors() {
        let cases = [
            (
                "resolution = 0.1",
                "resolution = 2.0",
                "t.toml: resolution: 2.0 m is outside (0.01, 1.0]",
            ),
            (
                "resolution = 0.1",
                "resolution = 0.01",
                "t.toml: resolution: 0.01 m is outside",
            ),
            (
                "max = [4.0, 3.0, 2.5]",
                "max = [4.0, 3.05, 2.5]",
                "t.toml: bounds: extent.y 3.05 m is not a whole",
            ),
            (
                "max = [4.0, 3.0, 2.5]",
                "max = [4.0, -3.0, 2.5]",
                "t.toml: bounds: min.y 0.0 >= max.y -3.0",
            ),
            (
                "max = [4.0, 3.0, 2.5]",
                "max = [60.0, 3.0, 2.5]",
                "t.toml: bounds: 600 voxels along x",
            ),
            (
                "max = [4.0, 3.0, 2.5]",
                "max = [50.0, 50.0, 10.0]",
                "t.toml: bounds: 500×500×100",
            ),
            (
                "position = [2.0, 1.5, 1.2]",
                "position = [2.0, 1.5, 0.3]",
                "t.toml: start: position [2.0, 1.5, 0.3] is within 0.3 m of box[0] (line 10)",
            ),
            (
                "position = [2.0, 1.5, 1.2]",
                "position = [5.0, 1.5, 1.2]",
                "t.toml: start: position [5.0, 1.5, 1.2] is not inside the bounds",
            ),
            (
                "max = [4, 3, 0.1]",
                "max = [4, 3, nan]",
                "t.toml: box[0]: max.z is NaN (line 10)",
            ),
            ("name = \"minimal\"", "name = \" \"", "t.toml: name: is empty"),
        ];
        for (from, to, expected) in cases {
            let text = MINIMAL.replace(from, to);
            assert_ne!(text, MINIMAL, "{from}");
            let err = error_of(&text);
            assert!(err.starts_with(expected), "{err}\n  expected: {expected}");
        }
    }

    #[test]
    fn wrong_types_are_parse_errors() {
        let err = error_of(&MINIMAL.replace("yaw_deg = 90", "yaw_deg = \"north\""));
        assert!(err.starts_with("t.toml:9:11: "), "{err}");
        let err = error_of(&MINIMAL.replace("[start]\nposition = [2.0, 1.5, 1.2]\nyaw_deg = 90\n", ""));
        assert!(err.contains("missing field `start`"), "{err}");
    }

    /// Geometry rules the built-ins must follow so that the whole free space is visible to a
    /// level camera on a vehicle with 0.2 m clearance (see `scenarios/*.toml`).
    /// Ground truth of the built-in worlds, voxel by voxel (also used by the camera's
    /// visibility bound, `crate::sensors::camera`'s tests).
    pub(crate) mod builtin_geometry {
        use super::*;
        use crate::world::World;
        use nalgebra::Vector3;

        const SLIT: f32 = 0.7;
        const EPS: f32 = 1e-3;

        fn on_grid(x: f32) -> bool {
            ((x * 10.0) - (x * 10.0).round()).abs() < EPS
        }

        /// The built-in worlds, and the held-out worlds of `scenarios/heldout/` (loaded by
        /// path; written to check tuned constants on layouts no tuning saw), which follow the
        /// same rules.
        pub(crate) fn builtins() -> impl Iterator<Item = Scenario> {
            let heldout =
                ["clinic"].map(|n| format!("{}/scenarios/heldout/{n}.toml", env!("CARGO_MANIFEST_DIR")));
            builtin_names()
                .iter()
                .map(|n| Scenario::builtin(n).unwrap())
                .chain(heldout.into_iter().map(|p| Scenario::load(&p).unwrap()))
        }

        #[test]
        fn start_is_clear_of_every_box() {
            for s in builtins() {
                let d = s.world.distance_to_nearest_box(&s.start_position);
                assert!(d >= 0.6 - EPS, "{}: start {d} m from nearest box", s.name());
                let z = s.start_position.z;
                assert!((1.0..=1.3).contains(&z), "{}: start height {z}", s.name());
            }
        }

        #[test]
        fn coordinates_on_the_grid_and_bounds_at_origin() {
            for s in builtins() {
                assert_eq!(s.resolution, 0.1);
                assert_eq!(s.world.bounds.min, Point3::origin());
                for (i, b) in s.world.boxes.iter().chain([&s.world.bounds]).enumerate() {
                    for c in b.min.iter().chain(b.max.iter()) {
                        assert!(on_grid(*c), "{}: box[{i}] coordinate {c}", s.name());
                    }
                }
            }
        }

        /// Every cell in the outer 0.1 m layer of the bounds is solid: the shell is closed.
        #[test]
        fn shell_is_closed() {
            for s in builtins() {
                let [nx, ny, nz] = s.grid_dims();
                let r = s.resolution;
                for z in 0..nz {
                    for y in 0..ny {
                        for x in 0..nx {
                            let edge =
                                x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1 || z == nz - 1;
                            if edge {
                                let min = Point3::new(x as f32 * r, y as f32 * r, z as f32 * r);
                                let max = Point3::new(min.x + r, min.y + r, min.z + r);
                                assert!(
                                    s.world.cell_occupied(&min, &max),
                                    "{}: hole at {x},{y},{z}",
                                    s.name()
                                );
                            }
                        }
                    }
                }
            }
        }

        fn overlap_1d(a: (f32, f32), b: (f32, f32)) -> bool {
            a.0 < b.1 - EPS && b.0 < a.1 - EPS
        }

        /// Ground-truth occupancy of every voxel, x fastest.
        pub(crate) fn occupancy(s: &Scenario) -> Vec<bool> {
            let [nx, ny, nz] = s.grid_dims();
            let r = s.resolution;
            let mut occupied = Vec::with_capacity(nx * ny * nz);
            for z in 0..nz {
                for y in 0..ny {
                    for x in 0..nx {
                        let min = Point3::new(x as f32 * r, y as f32 * r, z as f32 * r);
                        occupied.push(s.world.cell_occupied(&min, &(min + Vector3::repeat(r))));
                    }
                }
            }
            occupied
        }

        /// The first run of free voxels along an axis, between two occupied voxels, that is
        /// shorter than 0.7 m: `(axis, first voxel, length)`.
        fn find_slit(s: &Scenario) -> Option<(char, [usize; 3], usize)> {
            let dims = s.grid_dims();
            let occupied = occupancy(s);
            let min_run = (SLIT / s.resolution).round() as usize;
            for axis in 0..3 {
                let (a1, a2) = ((axis + 1) % 3, (axis + 2) % 3);
                for i in 0..dims[a1] {
                    for j in 0..dims[a2] {
                        let mut run_start = None;
                        for k in 0..dims[axis] {
                            let mut v = [0; 3];
                            v[axis] = k;
                            v[a1] = i;
                            v[a2] = j;
                            let free = !occupied[v[0] + dims[0] * (v[1] + dims[1] * v[2])];
                            match (free, run_start) {
                                (true, None) => run_start = Some(k),
                                (false, Some(start)) => {
                                    if k - start < min_run {
                                        v[axis] = start;
                                        return Some((AXES[axis], v, k - start));
                                    }
                                    run_start = None;
                                }
                                _ => {}
                            }
                        }
                    }
                }
            }
            None
        }

        /// No slit: along every axis, each run of free voxels between two occupied ones is at
        /// least 0.7 m long (a 0.2 m vehicle cannot enter narrower gaps nor see into them).
        #[test]
        fn no_narrow_gaps() {
            for s in builtins() {
                assert_eq!(
                    find_slit(&s),
                    None,
                    "{}: (axis, voxel, length) of a slit",
                    s.name()
                );
            }
        }

        #[test]
        fn slit_detector_finds_a_slit() {
            let mut s = Scenario::builtin("apartment").unwrap();
            // A shelf 0.5 m in front of the living room's south wall.
            s.world
                .boxes
                .push(crate::world::Aabb::from_arrays([1.5, 0.7, 0.1], [2.5, 1.0, 1.5]));
            assert_eq!(find_slit(&s), Some(('y', [15, 2, 1], 5)));
        }

        /// Every box above the ground rests on another box or hangs from one (lintels): no
        /// typo in z leaves furniture floating.
        #[test]
        fn nothing_hovers() {
            for s in builtins() {
                let w = &s.world;
                let xy_overlap = |a: &crate::world::Aabb, b: &crate::world::Aabb| {
                    (0..2).all(|k| overlap_1d((a.min[k], a.max[k]), (b.min[k], b.max[k])))
                };
                for (i, b) in w.boxes.iter().enumerate() {
                    if b.min.z < EPS {
                        continue;
                    }
                    let attached = w.boxes.iter().any(|o| {
                        xy_overlap(o, b)
                            && ((o.max.z - b.min.z).abs() < EPS || (o.min.z - b.max.z).abs() < EPS)
                    });
                    assert!(attached, "{}: box[{i}] hovers", s.name());
                }
            }
        }

        /// Free cells reachable by a 0.2 m sphere from the start, as a flood fill over voxel
        /// centres.
        pub(crate) fn reachable_centres(s: &Scenario) -> Vec<bool> {
            let [nx, ny, nz] = s.grid_dims();
            let r = s.resolution;
            let centre = |x: usize, y: usize, z: usize| {
                Point3::new((x as f32 + 0.5) * r, (y as f32 + 0.5) * r, (z as f32 + 0.5) * r)
            };
            let idx = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
            let clear = |w: &World, x, y, z| !w.sphere_collides(&centre(x, y, z), 0.2);
            let mut seen = vec![false; nx * ny * nz];
            let p = s.start_position;
            let v0 = [p.x, p.y, p.z].map(|c| (c / r) as usize);
            let mut stack = vec![v0];
            seen[idx(v0[0], v0[1], v0[2])] = true;
            while let Some([x, y, z]) = stack.pop() {
                let neighbours = [
                    [x.wrapping_sub(1), y, z],
                    [x + 1, y, z],
                    [x, y.wrapping_sub(1), z],
                    [x, y + 1, z],
                    [x, y, z.wrapping_sub(1)],
                    [x, y, z + 1],
                ];
                for [a, b, c] in neighbours {
                    if a < nx && b < ny && c < nz && !seen[idx(a, b, c)] && clear(&s.world, a, b, c) {
                        seen[idx(a, b, c)] = true;
                        stack.push([a, b, c]);
                    }
                }
            }
            seen
        }

        /// Marks the voxels a ray from `o` along unit `d` passes through up to distance `t_end`
        /// (Amanatides–Woo), as the core's integrator would observe them.
        pub(crate) fn trace(
            o: &Point3<f32>,
            d: &Vector3<f32>,
            t_end: f32,
            r: f32,
            dims: [usize; 3],
            seen: &mut [bool],
        ) {
            let mut v = [0i64; 3];
            let mut step = [0i64; 3];
            let mut t_max = [f32::INFINITY; 3];
            let mut t_delta = [f32::INFINITY; 3];
            for i in 0..3 {
                v[i] = (o[i] / r).floor() as i64;
                step[i] = if d[i] > 0.0 { 1 } else { -1 };
                if d[i] != 0.0 {
                    let boundary = if d[i] > 0.0 {
                        (v[i] + 1) as f32 * r
                    } else {
                        v[i] as f32 * r
                    };
                    t_max[i] = (boundary - o[i]) / d[i];
                    t_delta[i] = r / d[i].abs();
                }
            }
            loop {
                if (0..3).any(|i| v[i] < 0 || v[i] >= dims[i] as i64) {
                    return;
                }
                seen[v[0] as usize + dims[0] * (v[1] as usize + dims[1] * v[2] as usize)] = true;
                let i = (0..3).min_by(|&a, &b| t_max[a].total_cmp(&t_max[b])).unwrap();
                if t_max[i] >= t_end {
                    return;
                }
                v[i] += step[i];
                t_max[i] += t_delta[i];
            }
        }

        /// Every room is reachable from the start (one probe point per room, incl. upstairs).
        #[test]
        fn every_room_is_reachable() {
            let probes: &[(&str, &[[f32; 3]])] = &[
                (
                    "apartment",
                    &[[2.0, 2.0, 1.2], [4.5, 2.0, 1.2], [2.0, 5.0, 1.2], [4.5, 5.5, 1.2]],
                ),
                (
                    "office",
                    &[
                        [10.0, 4.0, 1.2],
                        [2.0, 2.0, 1.2],
                        [6.0, 2.5, 1.2],
                        [10.0, 2.0, 1.2],
                        [3.0, 5.3, 1.2],
                        [9.0, 7.2, 1.2],
                    ],
                ),
                (
                    "two-level",
                    &[
                        [2.0, 7.0, 1.5],
                        [6.5, 2.0, 1.2],
                        [2.5, 1.2, 3.8],
                        [4.5, 7.0, 3.8],
                        [6.5, 3.0, 3.8],
                    ],
                ),
            ];
            for (name, points) in probes {
                let s = Scenario::builtin(name).unwrap();
                let reach = reachable_centres(&s);
                let [nx, ny, _] = s.grid_dims();
                for p in points.iter() {
                    let [x, y, z] = p.map(|c| (c / s.resolution) as usize);
                    assert!(reach[x + nx * (y + ny * z)], "{name}: {p:?} unreachable");
                }
            }
        }
    }
}
