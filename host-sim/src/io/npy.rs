//! NumPy `.npy` files for 3-D arrays (and 2-D `float32` images): reading over the
//! [`ndarray_npy`] crate's header parser, writing byte for byte as `numpy.save`.
//!
//! # Format
//!
//! A `.npy` file is
//!
//! ```text
//! b"\x93NUMPY" | major: u8 | minor: u8 | header_len | header (header_len bytes) | data
//! ```
//!
//! where `header_len` is a little-endian `u16` for format 1.0 and a little-endian `u32` for 2.0
//! and 3.0, and the header is a Python dict literal such as
//! `{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), }`, padded with spaces and ended
//! by `'\n'` (ASCII for 1.0 and 2.0, UTF-8 for 3.0).
//!
//! # Reading: what the crate does, what this module does
//!
//! [`ndarray_npy::npy::header::Header`] parses the header: magic string, version (1.0, 2.0,
//! 3.0), header length, encoding, the dict literal (with the `py_literal` crate, which parses
//! the Python literals NumPy reads with `ast.literal_eval`) and its three keys. The shape comes
//! back as `usize`s and the layout as C or Fortran order, with no arithmetic done on them (the
//! other candidate, `npyz`, multiplies the shape out unchecked while parsing, which panics on a
//! shape like `(2**64 - 1, 2, 1)` when overflow checks are on). This module then keeps the
//! rules the readers have always had:
//!
//! - C order only: a Fortran-order file is [`NpyError::FortranOrder`].
//! - [`read_u8`] takes `uint8` (`'|u1'`, `'<u1'`, `'>u1'`, `'=u1'`, `'u1'`) and `bool` (`'|b1'`
//!   and the same variants, or `'?'`; any non-zero byte reads as 1). [`read_f32`] and
//!   [`read_f32_image`] take `float32` in either byte order (`'<f4'`, `'>f4'`). The table is
//!   ours (the crate's own element readers take fewer spellings of `uint8` and reject bool bytes
//!   other than 0 and 1), and so is the conversion of the data bytes.
//! - Exactly three dimensions (an image: two, or three with a last axis of 1), a byte size that
//!   does not overflow `usize`, and a data section of exactly that size.
//!
//! Three checks run before the crate sees the header. The fixed preamble (magic, version, length)
//! is read here so that a short file says how many bytes it needs ([`NpyError::Truncated`]) and
//! so that a length field of 4 GiB in a 12-byte file is never allocated (the crate allocates the
//! header before reading it). Headers longer than 10 000 bytes are refused, as `numpy.load`
//! refuses them by default (`max_header_size`). And headers with more than four opening
//! brackets are refused: the crate's parser backtracks, so its time grows exponentially with
//! the nesting depth (twenty nested lists, a 50-byte header, take seconds). Counting every `{`,
//! `[` and `(`, inside strings too, bounds the depth without parsing anything; a NumPy header
//! for a simple dtype has two. Every malformed input yields an [`NpyError`] and no input
//! panics.
//!
//! # Writing
//!
//! [`write_u8`] (`'|u1'`), [`write_f32`] and [`write_f32_image`] (`'<f4'`) produce format 1.0,
//! C order, byte for byte what NumPy 2.x `numpy.save` writes for the same array: keys sorted, a
//! trailing `", "` before `}`, NumPy's 21-digit growth padding, then spaces and `'\n'` so that
//! magic, version, length and header together are a multiple of 64 bytes. That header is
//! formatted here, not by a crate: `ndarray_npy` writes `'shape': (4, 3, 2)}` without the
//! `", "` and the growth padding, and `npyz` writes `(4, 3, 2, ), }`. NumPy reads both, but
//! the label grids and fields this simulator writes are promised to be exactly NumPy's bytes.
//!
//! # Element order
//!
//! [`Array3`] stores its elements in C (row-major) order, the order NumPy uses for
//! `fortran_order: False`: the **last** index varies fastest. For `shape = [nx, ny, nz]`, element
//! `[x, y, z]` is `data[(x * ny + y) * nz + z]`, so `data` holds `[0, 0, 0], [0, 0, 1], …,
//! [0, 0, nz-1], [0, 1, 0], …, [nx-1, ny-1, nz-1]`. In NumPy terms `data` is
//! `a.ravel(order='C')` for the array `a` with `a.shape == (nx, ny, nz)`, and `a[x, y, z]` is the
//! element [`Array3::get`]`(x, y, z)` returns.

use std::fmt;
use std::path::{Path, PathBuf};

use ndarray_npy::npy::header::{Header, ParseHeaderError, ReadHeaderError};

/// The six bytes every `.npy` file starts with.
const MAGIC: &[u8; 6] = b"\x93NUMPY";
/// The alignment NumPy ≥ 1.9 pads the header to.
const ARRAY_ALIGN: usize = 64;
/// NumPy leaves room in the header for the growable axis to reach this many digits.
const GROWTH_AXIS_MAX_DIGITS: usize = 21;
/// At most this many characters of an input-derived string go into an error message.
const MAX_QUOTED: usize = 40;
/// The longest header read, in bytes: `numpy.load`'s default `max_header_size`.
const MAX_HEADER_LEN: usize = 10_000;
/// The most opening brackets (`{`, `[`, `(`, anywhere) a header may have. NumPy's header for a
/// simple dtype has 2 (the dict, the shape tuple); `[('a', '<u1')]` as a structured dtype adds 2.
const MAX_OPEN_BRACKETS: usize = 4;

/// A dense 3-D array in C (row-major) order.
///
/// For `shape = [nx, ny, nz]`, element `[x, y, z]` is `data[(x * ny + y) * nz + z]`: `z` varies
/// fastest, `x` slowest (see the [module documentation](self)). A well-formed array has
/// `data.len() == nx * ny * nz`; the readers only return well-formed arrays, and the writers
/// panic on arrays that are not.
#[derive(Debug, Clone, PartialEq)]
pub struct Array3<T> {
    /// `[nx, ny, nz]`: the extent along each axis, slowest-varying first.
    pub shape: [usize; 3],
    /// The elements in C order: `[x, y, z]` at `(x * ny + y) * nz + z`.
    pub data: Vec<T>,
}

impl<T> Array3<T> {
    /// Wraps `data` (in C order) as an array of `shape`; `None` if `data.len()` is not the
    /// product of `shape`.
    pub fn new(shape: [usize; 3], data: Vec<T>) -> Option<Self> {
        (element_count(&shape) == Some(data.len())).then_some(Self { shape, data })
    }

    /// Builds an array of `shape` whose element `[x, y, z]` is `f(x, y, z)`, calling `f` in C
    /// order.
    ///
    /// # Panics
    ///
    /// If the product of `shape` overflows `usize`.
    pub fn from_fn(shape: [usize; 3], mut f: impl FnMut(usize, usize, usize) -> T) -> Self {
        let n = element_count(&shape).expect("Array3::from_fn: shape product overflows usize");
        let mut data = Vec::with_capacity(n);
        for x in 0..shape[0] {
            for y in 0..shape[1] {
                for z in 0..shape[2] {
                    data.push(f(x, y, z));
                }
            }
        }
        Self { shape, data }
    }

    /// Number of elements, `data.len()`.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// Whether the array has no elements (some axis has extent 0).
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The position of `[x, y, z]` in `data`, `(x * ny + y) * nz + z`; `None` if an index is out
    /// of range for `shape`.
    pub fn index_of(&self, x: usize, y: usize, z: usize) -> Option<usize> {
        let [nx, ny, nz] = self.shape;
        if x >= nx || y >= ny || z >= nz {
            return None;
        }
        x.checked_mul(ny)?.checked_add(y)?.checked_mul(nz)?.checked_add(z)
    }

    /// Element `[x, y, z]`, or `None` if out of range.
    pub fn get(&self, x: usize, y: usize, z: usize) -> Option<&T> {
        self.data.get(self.index_of(x, y, z)?)
    }
}

/// Why a `.npy` file could not be read.
///
/// Every variant's [`Display`](fmt::Display) is a single line saying what was wrong.
#[derive(Debug)]
pub enum NpyError {
    /// The file could not be read from disk.
    Io {
        /// The path that was being read.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The input does not start with `\x93NUMPY`.
    BadMagic,
    /// The input ends inside the magic string, version, header length or header.
    Truncated {
        /// Bytes needed to hold everything up to the end of the part that is cut off.
        needed: usize,
        /// Bytes present.
        got: usize,
    },
    /// The format version is not 1.0, 2.0 or 3.0.
    UnsupportedVersion {
        /// Major version byte.
        major: u8,
        /// Minor version byte.
        minor: u8,
    },
    /// The header is not ASCII (formats 1.0 and 2.0) or not UTF-8 (format 3.0).
    HeaderEncoding {
        /// Major format version (1, 2 or 3).
        major: u8,
    },
    /// The header is not a dict literal with exactly the keys `'descr'`, `'fortran_order'` and
    /// `'shape'` holding a string, a bool and a tuple of integers; or it is longer than
    /// 10 000 bytes or has more than four opening brackets (see the
    /// [module documentation](self)). The `reason` is the crate's, reworded.
    MalformedHeader {
        /// What is wrong with it.
        reason: String,
    },
    /// The array is stored in Fortran (column-major) order, which this reader does not support.
    FortranOrder,
    /// The dtype is not one the reader accepts.
    UnsupportedDtype {
        /// The header's `'descr'`.
        found: String,
        /// What was accepted, e.g. `'|u1' or '|b1'`.
        expected: &'static str,
    },
    /// The array does not have exactly three dimensions.
    NotThreeD {
        /// The header's shape.
        shape: Vec<usize>,
    },
    /// The array's byte size, product(shape) × itemsize, overflows `usize`.
    ShapeOverflow {
        /// The header's shape.
        shape: [usize; 3],
        /// Bytes per element.
        itemsize: usize,
    },
    /// The data section is not exactly product(shape) × itemsize bytes long.
    DataLength {
        /// The header's shape.
        shape: [usize; 3],
        /// Bytes per element.
        itemsize: usize,
        /// product(shape) × itemsize.
        expected: usize,
        /// Bytes after the header.
        found: usize,
    },
}

impl fmt::Display for NpyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, source } => {
                write!(
                    f,
                    "cannot read {}: {}",
                    path.display(),
                    one_line(&source.to_string())
                )
            }
            Self::BadMagic => write!(f, "not a .npy file: it does not start with \\x93NUMPY"),
            Self::Truncated { needed, got } => {
                write!(
                    f,
                    ".npy file truncated in its header: need {needed} bytes, got {got}"
                )
            }
            Self::UnsupportedVersion { major, minor } => write!(
                f,
                "unsupported .npy format version {major}.{minor} (supported: 1.0, 2.0, 3.0)"
            ),
            Self::HeaderEncoding { major } => {
                let encoding = if *major >= 3 { "UTF-8" } else { "ASCII" };
                write!(f, ".npy header is not valid {encoding} (format {major}.0)")
            }
            Self::MalformedHeader { reason } => write!(f, "malformed .npy header: {}", one_line(reason)),
            Self::FortranOrder => {
                write!(
                    f,
                    "array is stored in Fortran order (fortran_order: True); only C order is supported"
                )
            }
            Self::UnsupportedDtype { found, expected } => {
                write!(f, "unsupported dtype '{}', expected {expected}", quoted(found))
            }
            Self::NotThreeD { shape } => {
                write!(f, "expected a 3-D array, got shape {}", ShapeDisplay(shape))
            }
            Self::ShapeOverflow { shape, itemsize } => write!(
                f,
                "array of shape {} with {itemsize}-byte items is too large: its size overflows usize",
                ShapeDisplay(shape)
            ),
            Self::DataLength {
                shape,
                itemsize,
                expected,
                found,
            } => write!(
                f,
                "data section is {found} bytes, expected {expected} for shape {} with {itemsize}-byte items",
                ShapeDisplay(shape)
            ),
        }
    }
}

impl std::error::Error for NpyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// A shape as Python prints a tuple: `()`, `(4,)`, `(4, 5)`.
struct ShapeDisplay<'a>(&'a [usize]);

impl fmt::Display for ShapeDisplay<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            [] => write!(f, "()"),
            [only] => write!(f, "({only},)"),
            [first, rest @ ..] => {
                write!(f, "({first}")?;
                for d in rest {
                    write!(f, ", {d}")?;
                }
                write!(f, ")")
            }
        }
    }
}

/// Collapses all whitespace runs to single spaces.
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// An input-derived string made safe for a one-line message: escaped and shortened.
fn quoted(s: &str) -> String {
    let mut out: String = s.chars().take(MAX_QUOTED).flat_map(char::escape_debug).collect();
    if s.chars().nth(MAX_QUOTED).is_some() {
        out.push('…');
    }
    out
}

/// The exact product of `shape` (0 if any axis is 0, even if the others would overflow), `None`
/// on overflow.
fn element_count(shape: &[usize]) -> Option<usize> {
    if shape.contains(&0) {
        return Some(0);
    }
    shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// Reads a 3-D `uint8` (or `bool`, as 0/1) array from the bytes of a `.npy` file.
///
/// Accepts dtypes `'|u1'`, `'<u1'`, `'>u1'`, `'=u1'`, `'u1'` and `'|b1'`, `'<b1'`, `'>b1'`,
/// `'=b1'`, `'b1'`, `'?'`; a `bool` byte that is not 0 reads as 1. See the
/// [module documentation](self) for the formats and headers accepted.
pub fn read_u8(bytes: &[u8]) -> Result<Array3<u8>, NpyError> {
    let (shape, kind, data) = read_raw(bytes, u8_kind, "'|u1' or '|b1'")?;
    let data = match kind {
        U8Kind::U8 => data.to_vec(),
        U8Kind::Bool => data.iter().map(|&b| u8::from(b != 0)).collect(),
    };
    Ok(Array3 { shape, data })
}

/// Reads the `.npy` file at `path` with [`read_u8`].
pub fn read_u8_file(path: impl AsRef<Path>) -> Result<Array3<u8>, NpyError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| NpyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    read_u8(&bytes)
}

/// One `float32` from 4 bytes of a `.npy` body.
fn f32_of(c: &[u8], big_endian: bool) -> f32 {
    let b = [c[0], c[1], c[2], c[3]];
    if big_endian {
        f32::from_be_bytes(b)
    } else {
        f32::from_le_bytes(b)
    }
}

/// Reads a 3-D `float32` array (`'<f4'` or `'>f4'`) from the bytes of a `.npy` file.
pub fn read_f32(bytes: &[u8]) -> Result<Array3<f32>, NpyError> {
    let (shape, big_endian, data) = read_raw(bytes, f32_kind, "'<f4' or '>f4'")?;
    let data = data.chunks_exact(4).map(|c| f32_of(c, big_endian)).collect();
    Ok(Array3 { shape, data })
}

#[derive(Clone, Copy)]
enum U8Kind {
    U8,
    Bool,
}

/// The element kind and item size of a `descr` [`read_u8`] accepts.
fn u8_kind(descr: &str) -> Option<(U8Kind, usize)> {
    match descr {
        "|u1" | "<u1" | ">u1" | "=u1" | "u1" => Some((U8Kind::U8, 1)),
        "|b1" | "<b1" | ">b1" | "=b1" | "b1" | "?" => Some((U8Kind::Bool, 1)),
        _ => None,
    }
}

/// Whether a `descr` [`read_f32`] accepts is big-endian, and its item size.
fn f32_kind(descr: &str) -> Option<(bool, usize)> {
    match descr {
        "<f4" => Some((false, 4)),
        ">f4" => Some((true, 4)),
        _ => None,
    }
}

/// Reads a `float32` image: shape `(height, width)` or `(height, width, 1)`. Returns
/// `(height, width, data)` in row-major order.
pub fn read_f32_image(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), NpyError> {
    let (header, data) = split_header(bytes)?;
    let Some((big_endian, _)) = f32_kind(&header.descr) else {
        return Err(NpyError::UnsupportedDtype {
            found: header.descr,
            expected: "'<f4' or '>f4'",
        });
    };
    if header.fortran_order {
        return Err(NpyError::FortranOrder);
    }
    let (h, w) = match header.shape.as_slice() {
        &[h, w] | &[h, w, 1] => (h, w),
        _ => return Err(NpyError::NotThreeD { shape: header.shape }),
    };
    let shape = [h, w, 1];
    let expected = h
        .checked_mul(w)
        .and_then(|n| n.checked_mul(4))
        .ok_or(NpyError::ShapeOverflow { shape, itemsize: 4 })?;
    if data.len() != expected {
        return Err(NpyError::DataLength {
            shape,
            itemsize: 4,
            expected,
            found: data.len(),
        });
    }
    let values = data.chunks_exact(4).map(|c| f32_of(c, big_endian)).collect();
    Ok((h, w, values))
}

/// Parses and validates everything but the element values: returns the shape, the element kind
/// and the data section, whose length is checked to be product(shape) × itemsize.
fn read_raw<'a, K>(
    bytes: &'a [u8],
    kind_of: fn(&str) -> Option<(K, usize)>,
    expected: &'static str,
) -> Result<([usize; 3], K, &'a [u8]), NpyError> {
    let (header, data) = split_header(bytes)?;
    let Some((kind, itemsize)) = kind_of(&header.descr) else {
        return Err(NpyError::UnsupportedDtype {
            found: header.descr,
            expected,
        });
    };
    if header.fortran_order {
        return Err(NpyError::FortranOrder);
    }
    let shape: [usize; 3] = match header.shape.as_slice() {
        &[nx, ny, nz] => [nx, ny, nz],
        _ => return Err(NpyError::NotThreeD { shape: header.shape }),
    };
    let expected_len = element_count(&shape)
        .and_then(|n| n.checked_mul(itemsize))
        .ok_or(NpyError::ShapeOverflow { shape, itemsize })?;
    if data.len() != expected_len {
        return Err(NpyError::DataLength {
            shape,
            itemsize,
            expected: expected_len,
            found: data.len(),
        });
    }
    Ok((shape, kind, data))
}

/// What the readers need from a header.
struct HeaderInfo {
    /// The dtype string, e.g. `'|u1'` (a structured dtype's list is refused earlier).
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Checks the preamble and the header's size and brackets, has [`Header`] parse the header and
/// returns what it says with the bytes after it.
fn split_header(bytes: &[u8]) -> Result<(HeaderInfo, &[u8]), NpyError> {
    let got = bytes.len();
    let magic_seen = got.min(MAGIC.len());
    if bytes.get(..magic_seen) != MAGIC.get(..magic_seen) {
        return Err(NpyError::BadMagic);
    }
    let (major, minor) = match (bytes.get(6), bytes.get(7)) {
        (Some(&major), Some(&minor)) => (major, minor),
        _ => return Err(NpyError::Truncated { needed: 8, got }),
    };
    let len_size = match (major, minor) {
        (1, 0) => 2,
        (2, 0) | (3, 0) => 4,
        _ => return Err(NpyError::UnsupportedVersion { major, minor }),
    };
    let start = 8 + len_size;
    let header_len = match bytes.get(8..start) {
        Some(&[a, b]) => usize::from(u16::from_le_bytes([a, b])),
        Some(&[a, b, c, d]) => usize::try_from(u32::from_le_bytes([a, b, c, d])).unwrap_or(usize::MAX),
        _ => return Err(NpyError::Truncated { needed: start, got }),
    };
    let end = start.saturating_add(header_len);
    let Some(text) = bytes.get(start..end) else {
        return Err(NpyError::Truncated { needed: end, got });
    };
    if header_len > MAX_HEADER_LEN {
        return Err(malformed(format!(
            "it is {header_len} bytes long, more than the {MAX_HEADER_LEN} numpy.load reads by default"
        )));
    }
    let brackets = text.iter().filter(|b| matches!(b, b'{' | b'[' | b'(')).count();
    if brackets > MAX_OPEN_BRACKETS {
        return Err(malformed(format!(
            "it has {brackets} opening brackets, more than {MAX_OPEN_BRACKETS} (a NumPy header has 2)"
        )));
    }
    let mut rest = bytes;
    let header = Header::from_reader(&mut rest).map_err(|err| match err {
        // The whole header is there (checked above), so reading it from the slice cannot fail.
        ReadHeaderError::Io(_) => NpyError::Truncated { needed: end, got },
        ReadHeaderError::Parse(err) => header_error(err, major),
    })?;
    let descr = match header.type_descriptor.as_string() {
        Some(descr) => descr.clone(),
        None if header.type_descriptor.is_list() => {
            return Err(NpyError::UnsupportedDtype {
                found: "[…] (a structured dtype)".into(),
                expected: "a simple dtype",
            })
        }
        None => {
            return Err(malformed(format!(
                "'descr' is not a string: {}",
                clipped(&header.type_descriptor.to_string(), MAX_QUOTED)
            )))
        }
    };
    let info = HeaderInfo {
        descr,
        fortran_order: header.layout.is_fortran(),
        shape: header.shape,
    };
    Ok((info, rest))
}

/// The [`NpyError`] for the crate's reason to refuse a header of format `major`.0.
fn header_error(err: ParseHeaderError, major: u8) -> NpyError {
    match err {
        ParseHeaderError::MagicString => NpyError::BadMagic,
        ParseHeaderError::Version { major, minor } => NpyError::UnsupportedVersion { major, minor },
        ParseHeaderError::NonAscii | ParseHeaderError::Utf8Parse(_) => NpyError::HeaderEncoding { major },
        ParseHeaderError::MissingNewline => malformed("it does not end with '\\n'"),
        ParseHeaderError::DictParse(err) => malformed(format!(
            "not a Python literal: {}",
            clipped(&syntax_summary(&err.to_string()), 4 * MAX_QUOTED)
        )),
        ParseHeaderError::MetaNotDict(value) => {
            malformed(format!("not a dict: {}", clipped(&value.to_string(), MAX_QUOTED)))
        }
        ParseHeaderError::UnknownKey(key) => malformed(format!(
            "unexpected key {}",
            clipped(&key.to_string(), MAX_QUOTED)
        )),
        // ndarray-npy 0.10 names the missing 'shape' "shaper".
        ParseHeaderError::MissingKey(key) => {
            let key = if key == "shaper" { "shape" } else { key.as_str() };
            malformed(format!("missing key '{key}'"))
        }
        ParseHeaderError::IllegalValue { key, value } => {
            let wanted = match key.as_str() {
                "fortran_order" => "True or False",
                "shape" => "a tuple of non-negative integers that fit in usize",
                _ => "valid",
            };
            malformed(format!(
                "'{key}' is not {wanted}: {}",
                clipped(&value.to_string(), MAX_QUOTED)
            ))
        }
        ParseHeaderError::HeaderLengthOverflow(len) => {
            malformed(format!("its length {len} does not fit in usize"))
        }
    }
}

/// `at LINE:COLUMN, expected …` from a syntax error the way `py_literal` shows it (pest's
/// ` --> 1:29`, the header line, a caret, `= expected value` on separate lines); anything else
/// as it is.
fn syntax_summary(message: &str) -> String {
    let at = message
        .lines()
        .find_map(|l| l.split_once("--> ").map(|(_, at)| at.trim()));
    let what = message.lines().find_map(|l| l.trim().strip_prefix("= "));
    match (at, what) {
        (Some(at), Some(what)) => format!("at {at}, {what}"),
        _ => message.to_string(),
    }
}

fn malformed(reason: impl Into<String>) -> NpyError {
    NpyError::MalformedHeader {
        reason: reason.into(),
    }
}

/// Input-derived text made safe for a one-line message: whitespace runs collapsed, other control
/// characters escaped, at most `max` characters kept.
fn clipped(s: &str, max: usize) -> String {
    let line = one_line(s);
    let mut out = String::new();
    for c in line.chars().take(max) {
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    if line.chars().nth(max).is_some() {
        out.push('…');
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------------

/// Writes a 2-D `float32` image of `height × width` (row-major) as a `.npy` file of shape
/// `(height, width)`, as `numpy.save` would.
///
/// # Panics
///
/// If `data.len()` is not `height × width`.
pub fn write_f32_image(height: usize, width: usize, data: &[f32]) -> Vec<u8> {
    assert_eq!(
        height * width,
        data.len(),
        "write_f32_image: {height} x {width} != {}",
        data.len()
    );
    let mut out = header_bytes_for("<f4", &[height, width], data.len() * 4);
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Writes `arr` as a `.npy` file (format 1.0, dtype `'<f4'`, C order), byte for byte as NumPy
/// 2.x `numpy.save` would.
///
/// # Panics
///
/// If `arr.data.len()` is not the product of `arr.shape`.
pub fn write_f32(arr: &Array3<f32>) -> Vec<u8> {
    check_len(arr);
    let mut out = header_bytes("<f4", arr.shape, arr.data.len() * 4);
    for v in &arr.data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Writes `arr` as a `.npy` file (format 1.0, dtype `'|u1'`, C order), byte for byte as NumPy
/// 2.x `numpy.save` would.
///
/// # Panics
///
/// If `arr.data.len()` is not the product of `arr.shape`.
pub fn write_u8(arr: &Array3<u8>) -> Vec<u8> {
    check_len(arr);
    let mut out = header_bytes("|u1", arr.shape, arr.data.len());
    out.extend_from_slice(&arr.data);
    out
}

fn check_len<T>(arr: &Array3<T>) {
    assert_eq!(
        element_count(&arr.shape),
        Some(arr.data.len()),
        "npy: Array3 of shape {:?} holds {} elements",
        arr.shape,
        arr.data.len()
    );
}

/// Magic, version, header length and the padded header for a C-order array, with capacity for
/// `data_len` more bytes.
fn header_bytes(descr: &str, shape: [usize; 3], data_len: usize) -> Vec<u8> {
    header_bytes_for(descr, &shape, data_len)
}

/// [`header_bytes`] for any number (≥ 2) of dimensions.
fn header_bytes_for(descr: &str, shape: &[usize], data_len: usize) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': False, 'shape': ({}), }}",
        dims.join(", ")
    );
    // Room for the growable (first, in C order) axis to be rewritten in place with more digits.
    let digits = dims.first().map_or(1, String::len);
    header.extend(std::iter::repeat_n(
        ' ',
        GROWTH_AXIS_MAX_DIGITS.saturating_sub(digits),
    ));
    // NumPy pads with 1..=64 bytes (a full 64 when already aligned), the last being '\n'.
    let hlen = header.len() + 1;
    let (version, prefix_len) = if 10 + hlen + ARRAY_ALIGN <= usize::from(u16::MAX) {
        (1u8, 10)
    } else {
        (2u8, 12) // Unreachable for three dimensions, but NumPy's rule nonetheless.
    };
    let pad = ARRAY_ALIGN - (prefix_len + hlen) % ARRAY_ALIGN;
    let total = hlen + pad;
    let mut out = Vec::with_capacity(prefix_len + total + data_len);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[version, 0]);
    match u16::try_from(total) {
        Ok(len) if version == 1 => out.extend_from_slice(&len.to_le_bytes()),
        _ => out.extend_from_slice(&(total as u32).to_le_bytes()),
    }
    out.extend_from_slice(header.as_bytes());
    out.resize(prefix_len + total - 1, b' ');
    out.push(b'\n');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures")
            .join(name)
    }

    /// The label grid in `tests/fixtures/labels_4x3x2.npy`, `LABELS[x][y][z]` as in
    /// `make_fixtures.py`.
    const LABELS: [[[u8; 2]; 3]; 4] = [
        [[1, 1], [1, 2], [1, 1]],
        [[1, 1], [1, 1], [1, 2]],
        [[1, 0], [2, 0], [1, 0]],
        [[2, 0], [0, 0], [0, 0]],
    ];

    /// A `.npy` file with an arbitrary header text and version.
    fn npy_with_header(major: u8, header: &str, data: &[u8]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[major, 0]);
        if major == 1 {
            out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn u8_header(dict: &str) -> Vec<u8> {
        npy_with_header(1, &format!("{dict}\n"), &[7; 24])
    }

    #[test]
    fn array3_order_is_c_order() {
        let a = Array3::from_fn([4, 3, 2], |x, y, z| (100 * x + 10 * y + z) as u16);
        assert_eq!(a.len(), 24);
        assert_eq!(&a.data[..4], &[0, 1, 10, 11]);
        for x in 0..4 {
            for y in 0..3 {
                for z in 0..2 {
                    let i = (x * 3 + y) * 2 + z;
                    assert_eq!(a.index_of(x, y, z), Some(i));
                    assert_eq!(a.get(x, y, z), Some(&a.data[i]));
                    assert_eq!(a.data[i] as usize, 100 * x + 10 * y + z);
                }
            }
        }
        assert_eq!(a.get(4, 0, 0), None);
        assert_eq!(a.get(0, 3, 0), None);
        assert_eq!(a.get(0, 0, 2), None);
        assert!(Array3::new([4, 3, 2], vec![0u8; 23]).is_none());
        assert!(Array3::new([usize::MAX, 2, 1], Vec::<u8>::new()).is_none());
        assert!(Array3::new([usize::MAX, usize::MAX, 0], Vec::<u8>::new()).is_some());
        assert!(Array3::new([0, 3, 2], Vec::<u8>::new()).unwrap().is_empty());
    }

    #[test]
    fn fixture_labels_parses() {
        let a = read_u8_file(fixture("labels_4x3x2.npy")).unwrap();
        assert_eq!(a.shape, [4, 3, 2]);
        let flat: Vec<u8> = LABELS.iter().flatten().flatten().copied().collect();
        assert_eq!(a.data, flat);
        for (x, plane) in LABELS.iter().enumerate() {
            for (y, row) in plane.iter().enumerate() {
                for (z, &v) in row.iter().enumerate() {
                    assert_eq!(a.get(x, y, z), Some(&v), "[{x}, {y}, {z}]");
                }
            }
        }
        // x = 0 is free except [0, 1, 1]; unknown voxels exist.
        assert_eq!(a.get(0, 1, 1), Some(&2));
        let x0_occupied = (0..3)
            .flat_map(|y| (0..2).map(move |z| (y, z)))
            .filter(|&(y, z)| a.get(0, y, z) == Some(&2));
        assert_eq!(x0_occupied.count(), 1);
        assert!(a.data.contains(&0));
    }

    #[test]
    fn writer_matches_numpy_bytes_of_fixture() {
        let bytes = std::fs::read(fixture("labels_4x3x2.npy")).unwrap();
        let a = read_u8(&bytes).unwrap();
        assert_eq!(write_u8(&a), bytes);
    }

    #[test]
    fn fixture_fortran_order_is_rejected() {
        let err = read_u8_file(fixture("labels_4x3x2_fortran.npy")).unwrap_err();
        assert!(matches!(err, NpyError::FortranOrder), "{err}");
    }

    #[test]
    fn round_trip_u8() {
        for shape in [[4, 3, 2], [1, 1, 1], [0, 5, 7], [3, 0, 0], [12345, 2, 1]] {
            let a = Array3::from_fn(shape, |x, y, z| (x * 7 + y * 3 + z) as u8);
            let bytes = write_u8(&a);
            assert_eq!(read_u8(&bytes).unwrap(), a);
            assert!(matches!(read_f32(&bytes), Err(NpyError::UnsupportedDtype { .. })));
        }
    }

    #[test]
    fn round_trip_f32() {
        let special = [
            0.0,
            -0.0,
            1.5,
            f32::MIN_POSITIVE,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let a = Array3::from_fn([2, 2, 2], |x, y, z| special[(x * 2 + y) * 2 + z]);
        let back = read_f32(&write_f32(&a)).unwrap();
        assert_eq!(back.shape, a.shape);
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back.data), bits(&a.data));

        let b = Array3::from_fn([5, 1, 3], |x, y, z| x as f32 * 0.25 - y as f32 + z as f32 * 1e-3);
        let bytes = write_f32(&b);
        assert_eq!(read_f32(&bytes).unwrap(), b);
        assert!(matches!(read_u8(&bytes), Err(NpyError::UnsupportedDtype { .. })));
    }

    #[test]
    fn written_header_is_numpy_layout() {
        for shape in [
            [4, 3, 2],
            [1, 1, 1],
            [1234567890, 0, 9],
            [usize::MAX, usize::MAX, 0],
        ] {
            let n = element_count(&shape).unwrap();
            let a = Array3 {
                shape,
                data: vec![5u8; n],
            };
            let bytes = write_u8(&a);
            assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
            let hlen = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
            assert_eq!((10 + hlen) % 64, 0, "{shape:?}");
            assert_eq!(bytes.len(), 10 + hlen + n);
            assert_eq!(bytes[10 + hlen - 1], b'\n');
            let text = std::str::from_utf8(&bytes[10..10 + hlen - 1]).unwrap();
            let dict = text.trim_end_matches(' ');
            assert_eq!(
                dict,
                format!(
                    "{{'descr': '|u1', 'fortran_order': False, 'shape': ({}, {}, {}), }}",
                    shape[0], shape[1], shape[2]
                )
            );
            // The growth padding: at least 21 - digits(shape[0]) spaces after '}'.
            assert!(text.len() - dict.len() >= 21 - shape[0].to_string().len());
            assert_eq!(read_u8(&bytes).unwrap(), a);
        }
        // The fixture's header: 10 + 118 = 128 (the growth padding pushes it past 64).
        let bytes = write_u8(&Array3::from_fn([4, 3, 2], |_, _, _| 0));
        assert_eq!(u16::from_le_bytes([bytes[8], bytes[9]]), 118);
    }

    #[test]
    fn flexible_headers_are_accepted() {
        let ok = [
            // NumPy's own form, unpadded (no alignment at all is fine too).
            "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), }",
            // Any key order, double quotes, no trailing comma, odd whitespace.
            "{\"shape\":(4,3,2),\"fortran_order\":False,\"descr\":\"<u1\"}",
            " {\t'fortran_order' : False , 'shape' : ( 4 , 3 , 2 , ) , 'descr' : 'u1' ,}  ",
            "{'descr': '=u1', 'fortran_order': False, 'shape': (4, 3, 2)}",
            // Python literals NumPy's `ast.literal_eval` takes too: a hex integer, a repeated
            // key (the last one counts).
            "{'descr': '<f8', 'fortran_order': False, 'shape': (0x4, 3, 2), 'descr': '|u1'}",
        ];
        for dict in ok {
            let a = read_u8(&u8_header(dict)).unwrap_or_else(|e| panic!("{dict}: {e}"));
            assert_eq!(a.shape, [4, 3, 2]);
            assert_eq!(a.data, vec![7; 24]);
        }
        // Old NumPy: 16-byte alignment, no growth padding.
        let dict = "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), }";
        let mut header = dict.to_string();
        while !(10 + header.len() + 1).is_multiple_of(16) {
            header.push(' ');
        }
        header.push('\n');
        assert_eq!(
            read_u8(&npy_with_header(1, &header, &[1; 24])).unwrap().data,
            vec![1; 24]
        );
        // The longest header read: numpy.load's default limit, 10 000 bytes.
        let mut header = dict.to_string();
        header.extend(std::iter::repeat_n(' ', MAX_HEADER_LEN - dict.len() - 1));
        header.push('\n');
        assert_eq!(
            read_u8(&npy_with_header(2, &header, &[1; 24])).unwrap().shape,
            [4, 3, 2]
        );
        // Read by the hand-written parser this module had before it used the crate, refused by
        // the crate's: Python 2's long suffix, a line break inside the dict, no
        // '\n' at the end. NumPy has never written the last two; the first only under Python 2.
        for (header, want) in [
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4L, 3L, 2L), }\n",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1',\n'fortran_order': False, 'shape': (4, 3, 2), }\n",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), }",
                "does not end with '\\n'",
            ),
        ] {
            let err = read_u8(&npy_with_header(1, header, &[1; 24])).unwrap_err();
            assert!(
                matches!(err, NpyError::MalformedHeader { .. }) && err.to_string().contains(want),
                "{header:?}: {err}"
            );
        }
    }

    #[test]
    fn bool_reads_as_zero_one() {
        let data = [0u8, 1, 0, 1, 1, 0, 255, 2];
        for descr in ["|b1", "b1", "?"] {
            let header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (2, 2, 2), }}\n");
            let a = read_u8(&npy_with_header(1, &header, &data)).unwrap();
            assert_eq!(a.data, vec![0, 1, 0, 1, 1, 0, 1, 1]);
        }
    }

    /// Files as NumPy 2.4 writes them, byte for byte, each split into preamble, dict, padding,
    /// `'\n'` and data. Made with `numpy.save(f, a)`, or
    /// `numpy.lib.format.write_array(f, a, version=…)` for formats 2.0 and 3.0, for `a` =
    ///
    /// - `u8`: `np.arange(6, dtype=np.uint8).reshape(1, 2, 3)`
    /// - `f4`: `np.array([1.5, -2.0, np.inf, 0.0, -0.0, 3.25], dtype='<f4').reshape(3, 2, 1)`
    /// - `f4_big`: `np.array([1.5, -2.0], dtype='>f4').reshape(1, 1, 2)`
    /// - `b1`: `np.array([True, False, True, True]).reshape(2, 1, 2)`
    /// - `image`: `np.array([[0.5, np.inf, 2.0], [1.0, 0.0, -1.0]], dtype='<f4')`
    /// - `v2`, `v3`: `np.arange(4, dtype=np.uint8).reshape(1, 2, 2)`
    struct NumpyFiles {
        u8: Vec<u8>,
        f4: Vec<u8>,
        f4_big: Vec<u8>,
        b1: Vec<u8>,
        image: Vec<u8>,
        v2: Vec<u8>,
        v3: Vec<u8>,
    }

    fn numpy_files() -> NumpyFiles {
        let v1 = b"\x93NUMPY\x01\x00v\x00";
        let file = |parts: &[&[u8]]| parts.concat();
        NumpyFiles {
            u8: file(&[
                v1,
                b"{'descr': '|u1', 'fortran_order': False, 'shape': (1, 2, 3), }",
                &[b' '; 55],
                b"\n",
                &[0, 1, 2, 3, 4, 5],
            ]),
            f4: file(&[
                v1,
                b"{'descr': '<f4', 'fortran_order': False, 'shape': (3, 2, 1), }",
                &[b' '; 55],
                b"\n",
                &[0, 0, 192, 63, 0, 0, 0, 192, 0, 0, 128, 127],
                &[0, 0, 0, 0, 0, 0, 0, 128, 0, 0, 80, 64],
            ]),
            f4_big: file(&[
                v1,
                b"{'descr': '>f4', 'fortran_order': False, 'shape': (1, 1, 2), }",
                &[b' '; 55],
                b"\n",
                &[63, 192, 0, 0, 192, 0, 0, 0],
            ]),
            b1: file(&[
                v1,
                b"{'descr': '|b1', 'fortran_order': False, 'shape': (2, 1, 2), }",
                &[b' '; 55],
                b"\n",
                &[1, 0, 1, 1],
            ]),
            image: file(&[
                v1,
                b"{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }",
                &[b' '; 58],
                b"\n",
                &[0, 0, 0, 63, 0, 0, 128, 127, 0, 0, 0, 64],
                &[0, 0, 128, 63, 0, 0, 0, 0, 0, 0, 128, 191],
            ]),
            v2: file(&[
                b"\x93NUMPY\x02\x00t\x00\x00\x00",
                b"{'descr': '|u1', 'fortran_order': False, 'shape': (1, 2, 2), }",
                &[b' '; 53],
                b"\n",
                &[0, 1, 2, 3],
            ]),
            v3: file(&[
                b"\x93NUMPY\x03\x00t\x00\x00\x00",
                b"{'descr': '|u1', 'fortran_order': False, 'shape': (1, 2, 2), }",
                &[b' '; 53],
                b"\n",
                &[0, 1, 2, 3],
            ]),
        }
    }

    #[test]
    fn numpy_written_files_read_back() {
        let np = numpy_files();
        let u8 = read_u8(&np.u8).unwrap();
        assert_eq!((u8.shape, u8.data), ([1, 2, 3], vec![0, 1, 2, 3, 4, 5]));
        let f4 = read_f32(&np.f4).unwrap();
        assert_eq!(f4.shape, [3, 2, 1]);
        let want = [1.5, -2.0, f32::INFINITY, 0.0, -0.0, 3.25];
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&f4.data), bits(&want));
        let big = read_f32(&np.f4_big).unwrap();
        assert_eq!((big.shape, big.data), ([1, 1, 2], vec![1.5, -2.0]));
        let b1 = read_u8(&np.b1).unwrap();
        assert_eq!((b1.shape, b1.data), ([2, 1, 2], vec![1, 0, 1, 1]));
        let (h, w, image) = read_f32_image(&np.image).unwrap();
        assert_eq!((h, w), (2, 3));
        assert_eq!(image, vec![0.5, f32::INFINITY, 2.0, 1.0, 0.0, -1.0]);
        for file in [&np.v2, &np.v3] {
            let a = read_u8(file).unwrap();
            assert_eq!((a.shape, a.data), ([1, 2, 2], vec![0, 1, 2, 3]));
        }
        // A 3-D file is not an image unless its last axis is 1, and an image is not 3-D.
        assert!(matches!(
            read_f32_image(&np.f4_big),
            Err(NpyError::NotThreeD { .. })
        ));
        assert!(matches!(read_f32(&np.image), Err(NpyError::NotThreeD { .. })));
        let (h, w, column) = read_f32_image(&np.f4).unwrap();
        assert_eq!((h, w, column.len()), (3, 2, 6));
    }

    #[test]
    fn writers_match_numpy_bytes() {
        let np = numpy_files();
        let u8 = Array3::from_fn([1, 2, 3], |_, y, z| (y * 3 + z) as u8);
        assert_eq!(write_u8(&u8), np.u8);
        let f4 = Array3::new([3, 2, 1], vec![1.5, -2.0, f32::INFINITY, 0.0, -0.0, 3.25]).unwrap();
        assert_eq!(write_f32(&f4), np.f4);
        let image = [0.5, f32::INFINITY, 2.0, 1.0, 0.0, -1.0];
        assert_eq!(write_f32_image(2, 3, &image), np.image);
    }

    /// The guards in front of the crate's parser, whose time grows exponentially with nesting:
    /// none of these may take long.
    #[test]
    fn deeply_nested_headers_are_refused() {
        let header = |descr: &str| {
            let dict = format!("{{'descr': {descr}, 'fortran_order': False, 'shape': (4, 3, 2)}}");
            u8_header(&dict)
        };
        let deep = format!("{}1{}", "[".repeat(4000), "]".repeat(4000));
        // Closing brackets inside strings do not hide the real nesting.
        let hidden = "[[[']]]'".repeat(30) + &"]".repeat(90);
        for descr in [deep.as_str(), hidden.as_str(), "[[[[1]]]]"] {
            let err = read_u8(&header(descr)).unwrap_err();
            assert!(err.to_string().contains("opening brackets"), "{err}");
        }
        // The worst a header the guards let through can do: four nested braces (each tried as a
        // dict, then as a set) around a string as long as the size limit allows.
        let worst = format!("{{{{{{{{'{}'}}}}}}}}\n", "x".repeat(MAX_HEADER_LEN - 11));
        let started = std::time::Instant::now();
        let err = read_u8(&npy_with_header(1, &worst, &[])).unwrap_err();
        assert!(matches!(err, NpyError::MalformedHeader { .. }), "{err}");
        assert!(started.elapsed().as_secs() < 5, "{:?}", started.elapsed());
    }

    #[test]
    fn versions_2_and_3_are_read() {
        let header = "{'descr': '>f4', 'fortran_order': False, 'shape': (1, 1, 2), }\n";
        let data = [0x3f, 0x80, 0, 0, 0xc0, 0, 0, 0]; // 1.0, -2.0 big-endian
        for major in [2, 3] {
            let a = read_f32(&npy_with_header(major, header, &data)).unwrap();
            assert_eq!(a.data, vec![1.0, -2.0]);
        }
        // Format 3.0 allows UTF-8 in the header; 1.0 does not.
        let header = "{'descr': 'é', 'fortran_order': False, 'shape': (1, 1, 1), }\n";
        let err = read_u8(&npy_with_header(3, header, &[0])).unwrap_err();
        assert!(
            matches!(&err, NpyError::UnsupportedDtype { found, .. } if found == "é"),
            "{err}"
        );
        let err = read_u8(&npy_with_header(1, header, &[0])).unwrap_err();
        assert!(matches!(err, NpyError::HeaderEncoding { major: 1 }), "{err}");
    }

    /// Every variant, and its one-line message.
    #[test]
    fn every_error_variant() {
        let good = write_u8(&Array3::from_fn([4, 3, 2], |x, _, _| x as u8));
        let check = |result: Result<Array3<u8>, NpyError>, want: &str, pred: fn(&NpyError) -> bool| {
            let err = result.expect_err(want);
            let msg = err.to_string();
            assert!(pred(&err), "wrong variant for {want}: {err:?}");
            assert!(
                !msg.chars().any(char::is_control) && !msg.is_empty(),
                "message not one line: {msg:?}"
            );
            assert!(msg.contains(want), "message {msg:?} lacks {want:?}");
        };

        check(read_u8_file(fixture("does_not_exist.npy")), "cannot read", |e| {
            matches!(e, NpyError::Io { .. })
        });
        check(read_u8(b"PK\x03\x04 zip"), "not a .npy file", |e| {
            matches!(e, NpyError::BadMagic)
        });
        check(read_u8(b"\x93NUMPX\x01\x00"), "not a .npy file", |e| {
            matches!(e, NpyError::BadMagic)
        });
        check(read_u8(b""), "need 8 bytes, got 0", |e| {
            matches!(e, NpyError::Truncated { .. })
        });
        check(read_u8(b"\x93NUM"), "need 8 bytes, got 4", |e| {
            matches!(e, NpyError::Truncated { .. })
        });
        check(read_u8(&good[..9]), "need 10 bytes, got 9", |e| {
            matches!(e, NpyError::Truncated { .. })
        });
        check(read_u8(&good[..100]), "need 128 bytes, got 100", |e| {
            matches!(e, NpyError::Truncated { .. })
        });
        check(
            read_u8(b"\x93NUMPY\x02\x00\xff\xff\xff\xff{"),
            "need 4294967307 bytes",
            |e| matches!(e, NpyError::Truncated { .. }),
        );
        check(read_u8(b"\x93NUMPY\x04\x00\x10\x00"), "version 4.0", |e| {
            matches!(e, NpyError::UnsupportedVersion { major: 4, minor: 0 })
        });
        check(read_u8(b"\x93NUMPY\x01\x01\x10\x00"), "version 1.1", |e| {
            matches!(e, NpyError::UnsupportedVersion { major: 1, minor: 1 })
        });
        let mut latin1 = good.clone();
        latin1[100] = 0xe9;
        check(read_u8(&latin1), "not valid ASCII (format 1.0)", |e| {
            matches!(e, NpyError::HeaderEncoding { major: 1 })
        });
        let mut bad_utf8 = good.clone();
        bad_utf8[6] = 3;
        bad_utf8.splice(8..10, [118, 0, 0, 0]);
        bad_utf8[100] = 0xff;
        check(read_u8(&bad_utf8), "not valid UTF-8 (format 3.0)", |e| {
            matches!(e, NpyError::HeaderEncoding { major: 3 })
        });
        check(
            read_u8_file(fixture("labels_4x3x2_fortran.npy")),
            "Fortran order",
            |e| matches!(e, NpyError::FortranOrder),
        );
        check(
            read_u8(&u8_header(
                "{'descr': '<i8', 'fortran_order': False, 'shape': (4, 3, 2), }",
            )),
            "unsupported dtype '<i8', expected '|u1' or '|b1'",
            |e| matches!(e, NpyError::UnsupportedDtype { .. }),
        );
        check(
            read_u8(&u8_header(
                "{'descr': [('a', '<u1')], 'fortran_order': False, 'shape': (4, 3, 2)}",
            )),
            "structured dtype",
            |e| matches!(e, NpyError::UnsupportedDtype { .. }),
        );
        check(
            read_u8(&u8_header(
                "{'descr': 'a\\nb', 'fortran_order': False, 'shape': (4, 3, 2)}",
            )),
            "unsupported dtype 'a\\nb'",
            |e| matches!(e, NpyError::UnsupportedDtype { .. }),
        );
        for (shape, text) in [
            ("(4, 5)", "(4, 5)"),
            ("(24,)", "(24,)"),
            ("()", "()"),
            ("(4, 3, 2, 1)", "(4, 3, 2, 1)"),
        ] {
            let dict = format!("{{'descr': '|u1', 'fortran_order': False, 'shape': {shape}, }}");
            check(
                read_u8(&u8_header(&dict)),
                &format!("expected a 3-D array, got shape {text}"),
                |e| matches!(e, NpyError::NotThreeD { .. }),
            );
        }
        let huge = usize::MAX;
        let dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({huge}, 2, 1), }}");
        check(
            read_f32(&u8_header(&dict)).map(|_| Array3 {
                shape: [0; 3],
                data: vec![],
            }),
            "too large",
            |e| matches!(e, NpyError::ShapeOverflow { itemsize: 4, .. }),
        );
        let dict = format!(
            "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, 1, 1), }}",
            huge / 2
        );
        check(
            read_f32(&u8_header(&dict)).map(|_| Array3 {
                shape: [0; 3],
                data: vec![],
            }),
            "too large",
            |e| matches!(e, NpyError::ShapeOverflow { .. }),
        );
        check(
            read_u8(&good[..good.len() - 1]),
            "data section is 23 bytes, expected 24",
            |e| {
                matches!(
                    e,
                    NpyError::DataLength {
                        expected: 24,
                        found: 23,
                        ..
                    }
                )
            },
        );
        let mut long = good.clone();
        long.push(0);
        check(
            read_u8(&long),
            "data section is 25 bytes, expected 24 for shape (4, 3, 2)",
            |e| matches!(e, NpyError::DataLength { .. }),
        );

        let malformed_headers = [
            ("", "not a Python literal: at 1:1, expected value"),
            ("[1]", "not a dict: [1]"),
            ("{'descr': '|u1', 'fortran_order': False}", "missing key 'shape'"),
            (
                "{'shape': (4, 3, 2), 'fortran_order': False}",
                "missing key 'descr'",
            ),
            (
                "{'shape': (4, 3, 2), 'descr': '|u1'}",
                "missing key 'fortran_order'",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), 'x': 1}",
                "unexpected key 'x'",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), 7: 1}",
                "unexpected key 7",
            ),
            (
                "{'descr': 1, 'fortran_order': False, 'shape': (4, 3, 2)}",
                "'descr' is not a string: 1",
            ),
            (
                "{'descr': '|u1', 'fortran_order': 0, 'shape': (4, 3, 2)}",
                "'fortran_order' is not True or False: 0",
            ),
            (
                "{'descr': '|u1', 'fortran_order': false, 'shape': (4, 3, 2)}",
                "not a Python literal: at 1:35",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (24)}",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': [4, 3, 2]}",
                "'shape' is not a tuple of non-negative integers that fit in usize: [4, 3, 2]",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, -3, 2)}",
                "'shape' is not a tuple of non-negative integers",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3.0, 2)}",
                "'shape' is not a tuple of non-negative integers",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4,, 2)}",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2)",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2)} x",
                "not a Python literal",
            ),
            (
                "{'descr': '|u1 , 'fortran_order': False, 'shape': (4, 3, 2)}",
                "not a Python literal: at 1:18",
            ),
            (
                "{'descr' '|u1', 'fortran_order': False, 'shape': (4, 3, 2)}",
                "not a Python literal",
            ),
            (
                "{'descr': \"|u1', 'fortran_order': False, 'shape': (4, 3, 2)}",
                "not a Python literal",
            ),
            ("{descr: '|u1'}", "not a Python literal"),
            ("{,}", "not a Python literal"),
            (
                "{'shape': (99999999999999999999999, 3, 2)}",
                "'shape' is not a tuple of non-negative integers that fit in usize: (99999999999999999999999, 3, 2)",
            ),
            // Control characters from the input are escaped, long input is cut short.
            (
                "{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), '\x1b[2J': 1}",
                "unexpected key '\\u{1b}[2J'",
            ),
            (
                &format!("{{'{}': 1}}", "k".repeat(500)),
                "unexpected key 'kkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkkk…",
            ),
            // Guards in front of the crate's parser.
            (
                &format!("{{'descr': '|u1', 'fortran_order': False, 'shape': (4, 3, 2), }}{}", " ".repeat(9938)),
                "it is 10001 bytes long, more than the 10000 numpy.load reads by default",
            ),
            (
                "{'descr': [[[[1]]]], 'fortran_order': False, 'shape': (4, 3, 2)}",
                "it has 6 opening brackets, more than 4 (a NumPy header has 2)",
            ),
        ];
        for (dict, want) in malformed_headers {
            check(read_u8(&u8_header(dict)), want, |e| {
                matches!(e, NpyError::MalformedHeader { .. })
            });
        }
    }

    /// A small linear congruential generator (Knuth's MMIX constants).
    struct Lcg(u64);

    impl Lcg {
        fn next(&mut self) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            self.0 >> 33
        }

        fn below(&mut self, n: usize) -> usize {
            (self.next() % n as u64) as usize
        }
    }

    /// Both readers on `bytes`: any result is fine, but a returned array must be well formed.
    fn read_both(bytes: &[u8]) {
        if let Ok(a) = read_u8(bytes) {
            assert_eq!(element_count(&a.shape), Some(a.data.len()));
        }
        if let Ok(a) = read_f32(bytes) {
            assert_eq!(element_count(&a.shape), Some(a.data.len()));
        }
    }

    #[test]
    fn truncations_are_errors() {
        let files = [
            std::fs::read(fixture("labels_4x3x2.npy")).unwrap(),
            write_f32(&Array3::from_fn([3, 2, 2], |x, y, z| (x + y + z) as f32)),
        ];
        for file in &files {
            assert!(read_u8(file).is_ok() || read_f32(file).is_ok());
            for len in 0..file.len() {
                assert!(
                    read_u8(&file[..len]).is_err() && read_f32(&file[..len]).is_err(),
                    "prefix {len}"
                );
            }
        }
    }

    #[test]
    fn corrupted_inputs_never_panic() {
        let mut v3 = write_f32(&Array3::from_fn([2, 3, 1], |x, y, _| (x * y) as f32));
        v3[6] = 3;
        v3.splice(8..10, [v3[8], v3[9], 0, 0]);
        let seeds = [
            std::fs::read(fixture("labels_4x3x2.npy")).unwrap(),
            std::fs::read(fixture("labels_4x3x2_fortran.npy")).unwrap(),
            write_f32(&Array3::from_fn([3, 2, 2], |x, y, z| (x + y + z) as f32)),
            v3,
        ];
        const INTERESTING: &[u8] = b"'\"(),:{}[] \t\n0123456789TFLl-_\\\x00\x80\xc3\xa9\xff";
        let mut rng = Lcg(0x5eed_1234_abcd_0001);
        for round in 0..40_000 {
            let mut bytes = seeds[round % seeds.len()].clone();
            let header_end = 128.min(bytes.len());
            match rng.below(6) {
                0 => bytes.truncate(rng.below(bytes.len() + 1)),
                1 => {
                    for _ in 0..1 + rng.below(4) {
                        let i = rng.below(bytes.len());
                        bytes[i] = rng.next() as u8;
                    }
                }
                2 => {
                    for _ in 0..1 + rng.below(3) {
                        let i = rng.below(header_end);
                        bytes[i] = INTERESTING[rng.below(INTERESTING.len())];
                    }
                }
                3 => {
                    let i = rng.below(header_end);
                    if rng.below(2) == 0 {
                        bytes.remove(i);
                    } else {
                        bytes.insert(i, INTERESTING[rng.below(INTERESTING.len())]);
                    }
                }
                4 => {
                    // A random header length field.
                    let r = rng.next().to_le_bytes();
                    bytes[8] = r[0];
                    bytes[9] = r[1];
                    if bytes[6] != 1 {
                        bytes[10] = r[2];
                        bytes[11] = r[3] % 4;
                    }
                }
                _ => {
                    // A random header assembled from header-ish tokens.
                    const TOKENS: &[&str] = &[
                        "{",
                        "}",
                        "(",
                        ")",
                        "[",
                        "]",
                        ",",
                        ":",
                        " ",
                        "'descr'",
                        "'shape'",
                        "'fortran_order'",
                        "'|u1'",
                        "'<f4'",
                        "\"",
                        "'",
                        "True",
                        "False",
                        "0",
                        "3",
                        "2L",
                        "18446744073709551616",
                        "\\",
                        "é",
                        "\n",
                    ];
                    let mut header = String::new();
                    for _ in 0..rng.below(24) {
                        header.push_str(TOKENS[rng.below(TOKENS.len())]);
                    }
                    let data_len = rng.below(40);
                    bytes = npy_with_header(1 + rng.below(3) as u8, &header, &vec![1; data_len]);
                }
            }
            read_both(&bytes);
        }
    }
}
