//! PX4's ULog format: a streaming reader ([`Reader`]) and a writer ([`writer::Writer`]).
//!
//! A ULog file is a 16-byte header (`ULog` magic, a version byte, the start time in µs) and
//! a stream of messages, each a 3-byte header (`u16` size, `u8` type) and its payload. The
//! definitions section holds the flag bits (`B`), the message formats (`F`: `name:type
//! field;…`), information (`I`, `M`) and parameters (`P`, `Q`); the data section subscribes
//! topic instances to formats (`A`) and then carries their samples (`D`), text messages (`L`,
//! `C`), dropouts (`O`) and sync markers (`S`).
//!
//! Layouts differ between PX4 versions (v1.11 has no `timestamp_sample`; later ones add and
//! reorder fields), so every value is read **by field name** through the log's own format
//! records ([`Layout`]), never by a fixed offset.
//!
//! The reader never trusts the file: a truncated file ends the stream (flagged in
//! [`Stats::truncated`]); a damaged message is skipped, with the reader resynchronising on
//! the next sync marker where there is one ([`Stats::corrupt_bytes`]); formats that do not
//! parse, nest too deep or in a circle, or are larger than a message can carry are left out
//! ([`Stats::bad_formats`]); sizes and counts are checked before anything is allocated. The
//! only errors are a file that is not a ULog file, one that needs features this reader does
//! not know (unknown incompatible flag bits) and I/O failures.

pub mod writer;

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::rc::Rc;

/// The first seven bytes of every ULog file.
pub const MAGIC: [u8; 7] = [0x55, 0x4c, 0x6f, 0x67, 0x01, 0x12, 0x35];

/// The bytes of a sync message, which a reader can search for after damage.
pub const SYNC_MAGIC: [u8; 8] = [0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12];

/// Nesting depth of formats inside formats that the reader follows.
pub const MAX_NESTING: usize = 8;

/// Flattened fields a format may have once nested formats are expanded.
const MAX_FIELDS: usize = 1 << 14;

/// Bytes searched for a sync marker after a damaged message before the rest is given up.
const MAX_SYNC_SEARCH: u64 = 1 << 24;

/// A ULog file that cannot be read at all.
#[derive(Debug, thiserror::Error)]
pub enum UlogError {
    /// The file does not start with the ULog magic bytes.
    #[error("{path}: not a ULog file (it does not start with the ULog magic bytes)")]
    NotUlog {
        /// The file.
        path: PathBuf,
    },
    /// The file sets incompatible flag bits this reader does not know: its data cannot be
    /// parsed safely.
    #[error(
        "{path}: the log sets incompatible flag bits this reader does not know ({flags:#x}); it cannot be read safely"
    )]
    Incompatible {
        /// The file.
        path: PathBuf,
        /// The unknown bits of the first incompatibility byte and the others, as one number.
        flags: u64,
    },
    /// Reading failed.
    #[error("{path}: cannot read")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
}

/// A scalar type of a ULog field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldType {
    /// `int8_t`
    I8,
    /// `uint8_t`
    U8,
    /// `int16_t`
    I16,
    /// `uint16_t`
    U16,
    /// `int32_t`
    I32,
    /// `uint32_t`
    U32,
    /// `int64_t`
    I64,
    /// `uint64_t`
    U64,
    /// `float`
    F32,
    /// `double`
    F64,
    /// `bool`
    Bool,
    /// `char`
    Char,
}

impl FieldType {
    /// The type of a ULog type name, `None` for a nested format's name.
    pub fn parse(name: &str) -> Option<FieldType> {
        Some(match name {
            "int8_t" => FieldType::I8,
            "uint8_t" => FieldType::U8,
            "int16_t" => FieldType::I16,
            "uint16_t" => FieldType::U16,
            "int32_t" => FieldType::I32,
            "uint32_t" => FieldType::U32,
            "int64_t" => FieldType::I64,
            "uint64_t" => FieldType::U64,
            "float" => FieldType::F32,
            "double" => FieldType::F64,
            "bool" => FieldType::Bool,
            "char" => FieldType::Char,
            _ => return None,
        })
    }

    /// Its ULog name.
    pub fn name(self) -> &'static str {
        match self {
            FieldType::I8 => "int8_t",
            FieldType::U8 => "uint8_t",
            FieldType::I16 => "int16_t",
            FieldType::U16 => "uint16_t",
            FieldType::I32 => "int32_t",
            FieldType::U32 => "uint32_t",
            FieldType::I64 => "int64_t",
            FieldType::U64 => "uint64_t",
            FieldType::F32 => "float",
            FieldType::F64 => "double",
            FieldType::Bool => "bool",
            FieldType::Char => "char",
        }
    }

    /// Bytes of one element.
    pub fn size(self) -> usize {
        match self {
            FieldType::I8 | FieldType::U8 | FieldType::Bool | FieldType::Char => 1,
            FieldType::I16 | FieldType::U16 => 2,
            FieldType::I32 | FieldType::U32 | FieldType::F32 => 4,
            FieldType::I64 | FieldType::U64 | FieldType::F64 => 8,
        }
    }

    /// The element at the start of `b` as a number (`None` when `b` is too short).
    pub fn decode(self, b: &[u8]) -> Option<f64> {
        let b = b.get(..self.size())?;
        Some(match self {
            FieldType::I8 => f64::from(b[0] as i8),
            FieldType::U8 | FieldType::Char => f64::from(b[0]),
            FieldType::Bool => f64::from(u8::from(b[0] != 0)),
            FieldType::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            FieldType::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            FieldType::I32 => f64::from(i32::from_le_bytes(b.try_into().ok()?)),
            FieldType::U32 => f64::from(u32::from_le_bytes(b.try_into().ok()?)),
            FieldType::F32 => f64::from(f32::from_le_bytes(b.try_into().ok()?)),
            FieldType::I64 => i64::from_le_bytes(b.try_into().ok()?) as f64,
            FieldType::U64 => u64::from_le_bytes(b.try_into().ok()?) as f64,
            FieldType::F64 => f64::from_le_bytes(b.try_into().ok()?),
        })
    }
}

/// One field of a format, nested formats flattened (`parent.child`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Field {
    /// Its name (`gps_hvel`, `timestamp`, `sub.value`).
    pub name: String,
    /// Element type.
    pub ty: FieldType,
    /// Elements: 1 for a scalar, n for `type[n]`.
    pub count: usize,
    /// Whether it was declared as an array (`type[1]` is an array of one).
    pub array: bool,
    /// Byte offset in a sample.
    pub offset: usize,
}

/// A format with its fields' offsets: how to read a topic's samples by field name.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Layout {
    /// The format's name.
    pub name: String,
    /// Fields in order, nested formats flattened.
    pub fields: Vec<Field>,
    /// Bytes of a sample, trailing padding included.
    pub size: usize,
}

impl Layout {
    /// The field called `name`.
    pub fn field(&self, name: &str) -> Option<&Field> {
        self.fields.iter().find(|f| f.name == name)
    }

    /// Element `i` of `field` in the sample `payload` (`None` past the field or the sample).
    pub fn value(&self, payload: &[u8], field: &Field, i: usize) -> Option<f64> {
        if i >= field.count {
            return None;
        }
        let at = field.offset.checked_add(i.checked_mul(field.ty.size())?)?;
        field.ty.decode(payload.get(at..)?)
    }

    /// Element `i` of the field called `name`.
    pub fn get(&self, payload: &[u8], name: &str, i: usize) -> Option<f64> {
        self.value(payload, self.field(name)?, i)
    }

    /// The sample's `timestamp` (µs), exact.
    pub fn timestamp(&self, payload: &[u8]) -> Option<u64> {
        let f = self.field("timestamp")?;
        (f.ty == FieldType::U64)
            .then(|| payload.get(f.offset..f.offset + 8))
            .flatten()
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }

    /// The `u64` field `name` (a timestamp), exact.
    pub fn u64_field(&self, payload: &[u8], name: &str) -> Option<u64> {
        let f = self.field(name)?;
        (f.ty == FieldType::U64)
            .then(|| payload.get(f.offset..f.offset + 8))
            .flatten()
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }
}

/// The text of a format message split into its name and `(type, name)` fields, or `None`
/// when it is not of the form `name:type field;type field;…`.
pub fn split_format(text: &str) -> Option<(String, Vec<(String, String)>)> {
    let (name, rest) = text.split_once(':')?;
    if name.is_empty() {
        return None;
    }
    let mut fields = Vec::new();
    for part in rest.split(';') {
        let part = part.trim();
        if part.is_empty() {
            continue;
        }
        let (ty, field) = part.split_once(' ')?;
        fields.push((ty.trim().to_string(), field.trim().to_string()));
    }
    Some((name.to_string(), fields))
}

/// `type[n]` → (`type`, Some(n)); `type` → (`type`, None); `None` when malformed.
fn split_array(ty: &str) -> Option<(&str, Option<usize>)> {
    match ty.split_once('[') {
        None => Some((ty, None)),
        Some((base, rest)) => {
            let n = rest.strip_suffix(']')?.parse::<usize>().ok()?;
            Some((base, Some(n)))
        }
    }
}

/// Resolves format `name` against `formats` into a flat layout: nested formats expanded,
/// padding fields kept for their bytes but not listed. `None` when a type is unknown, the
/// nesting is deeper than [`MAX_NESTING`] or circular, or the sample would be larger than a
/// message can carry.
pub fn resolve(name: &str, formats: &HashMap<String, Vec<(String, String)>>) -> Option<Layout> {
    let mut fields = Vec::new();
    let size = flatten(name, "", 0, 0, formats, &mut fields)?;
    Some(Layout {
        name: name.to_string(),
        fields,
        size,
    })
}

fn flatten(
    name: &str,
    prefix: &str,
    base: usize,
    depth: usize,
    formats: &HashMap<String, Vec<(String, String)>>,
    out: &mut Vec<Field>,
) -> Option<usize> {
    if depth > MAX_NESTING {
        return None;
    }
    let mut offset = 0usize;
    for (ty, field) in formats.get(name)? {
        let (base_ty, n) = split_array(ty)?;
        let count = n.unwrap_or(1);
        let full = format!("{prefix}{field}");
        match FieldType::parse(base_ty) {
            Some(t) => {
                if !field.starts_with("_padding") {
                    if out.len() >= MAX_FIELDS {
                        return None;
                    }
                    out.push(Field {
                        name: full,
                        ty: t,
                        count,
                        array: n.is_some(),
                        offset: base.checked_add(offset)?,
                    });
                }
                offset = offset.checked_add(t.size().checked_mul(count)?)?;
            }
            None => {
                for i in 0..count {
                    let sub = if n.is_some() {
                        format!("{full}[{i}].")
                    } else {
                        format!("{full}.")
                    };
                    let start = base.checked_add(offset)?;
                    let size = flatten(base_ty, &sub, start, depth + 1, formats, out)?;
                    if size == 0 {
                        // A format without bytes cannot be a field (and an array of a
                        // billion of them would only cost time).
                        return None;
                    }
                    offset = offset.checked_add(size)?;
                    if offset > usize::from(u16::MAX) {
                        return None;
                    }
                }
            }
        }
        if offset > usize::from(u16::MAX) {
            return None;
        }
    }
    Some(offset)
}

/// One topic instance the log records (an `A` message resolved against its format).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Subscription {
    /// The id its data messages carry.
    pub msg_id: u16,
    /// The topic's instance (`multi_id`).
    pub multi_id: u8,
    /// The topic's name (its format's name).
    pub name: String,
    /// How to read its samples.
    pub layout: Rc<Layout>,
}

/// A value of an information or parameter message.
#[derive(Clone, Debug, PartialEq)]
pub enum InfoValue {
    /// A `char[n]` value.
    Text(String),
    /// A number (any integer or float type).
    Number(f64),
    /// Any other type, undecoded.
    Other,
}

impl InfoValue {
    fn decode(ty: &str, b: &[u8]) -> InfoValue {
        match split_array(ty) {
            Some(("char", Some(_))) => InfoValue::Text(
                String::from_utf8_lossy(b)
                    .trim_end_matches('\0')
                    .to_string(),
            ),
            Some((t, None)) => match FieldType::parse(t).and_then(|t| t.decode(b)) {
                Some(v) => InfoValue::Number(v),
                None => InfoValue::Other,
            },
            _ => InfoValue::Other,
        }
    }
}

/// One message of the stream, borrowed from the reader until the next call.
#[derive(Debug)]
pub enum Message<'a> {
    /// Information (`I`): `key` without its type.
    Info {
        /// The key's name.
        key: &'a str,
        /// Its value.
        value: InfoValue,
    },
    /// A parameter's value (`P`), initial (in the definitions) or changed in flight.
    Parameter {
        /// The parameter's name.
        name: &'a str,
        /// Its value.
        value: InfoValue,
        /// Set in the data section (a change while logging).
        changed: bool,
    },
    /// A topic instance was subscribed (`A`).
    Subscribed(&'a Subscription),
    /// A sample of a subscribed topic (`D`).
    Data {
        /// Its topic instance.
        sub: &'a Subscription,
        /// Its bytes, read through `sub.layout`.
        payload: &'a [u8],
    },
    /// A text message (`L` or `C`).
    Logging {
        /// Its level (`'0'`…`'7'` as in syslog, ASCII).
        level: u8,
        /// When (µs).
        timestamp: u64,
        /// The text.
        text: &'a str,
    },
    /// The logger dropped data for this long (`O`).
    Dropout {
        /// Milliseconds lost.
        ms: u16,
    },
}

/// What the reader met besides the messages it returned.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Whether the file ended inside a message (a cut log).
    pub truncated: bool,
    /// Bytes skipped because a message was damaged (0 in an intact file).
    pub corrupt_bytes: u64,
    /// Formats that could not be used (malformed, unknown type, too deep or too large).
    pub bad_formats: Vec<String>,
    /// Data messages of an unknown subscription or too short for their format.
    pub bad_data: u64,
    /// Dropouts (`O` messages) and the milliseconds they lost.
    pub dropouts: (u64, u64),
}

/// A streaming ULog reader: [`Reader::next_message`] returns one message at a time; memory does not
/// grow with the file.
pub struct Reader<R> {
    src: R,
    path: PathBuf,
    pos: u64,
    buf: Vec<u8>,
    formats: HashMap<String, Vec<(String, String)>>,
    subs: HashMap<u16, Subscription>,
    in_data: bool,
    /// Appended-data offsets still ahead (a log with `DATA_APPENDED` continues there).
    appended: Vec<u64>,
    done: bool,
    /// The log's version byte.
    pub version: u8,
    /// The start time in the header (µs).
    pub start_us: u64,
    /// What was skipped or damaged so far.
    pub stats: Stats,
}

impl Reader<BufReader<File>> {
    /// Opens `path` and reads its header.
    pub fn open(path: &Path) -> Result<Self, UlogError> {
        let file = File::open(path).map_err(|source| UlogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Reader::new(BufReader::with_capacity(1 << 16, file), path)
    }
}

/// Reads into `buf` as much of it as the source has; returns the bytes read.
fn fill(src: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match src.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

impl<R: Read + Seek> Reader<R> {
    /// A reader of `src` (named `path` in errors); reads the 16-byte header.
    pub fn new(mut src: R, path: &Path) -> Result<Self, UlogError> {
        let mut head = [0u8; 16];
        let n = fill(&mut src, &mut head).map_err(|source| UlogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        if n < 16 || head[..7] != MAGIC {
            return Err(UlogError::NotUlog {
                path: path.to_path_buf(),
            });
        }
        Ok(Reader {
            src,
            path: path.to_path_buf(),
            pos: 16,
            buf: Vec::with_capacity(1 << 16),
            formats: HashMap::new(),
            subs: HashMap::new(),
            in_data: false,
            appended: Vec::new(),
            done: false,
            version: head[7],
            start_us: u64::from_le_bytes(head[8..16].try_into().expect("8 bytes")),
            stats: Stats::default(),
        })
    }

    fn io(&self, source: std::io::Error) -> UlogError {
        UlogError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// The file being read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The subscription with data id `msg_id`.
    pub fn subscription(&self, msg_id: u16) -> Option<&Subscription> {
        self.subs.get(&msg_id)
    }

    /// Reads the next message's type and payload into `self.buf`; `None` at the end.
    fn raw(&mut self) -> Result<Option<u8>, UlogError> {
        loop {
            if self.done {
                return Ok(None);
            }
            let mut head = [0u8; 3];
            let n = fill(&mut self.src, &mut head).map_err(|e| self.io(e))?;
            let start = self.pos;
            if n < 3 {
                if !self.next_appended()? {
                    self.stats.truncated |= n > 0;
                    self.done = true;
                }
                continue;
            }
            let size = usize::from(u16::from_le_bytes([head[0], head[1]]));
            self.buf.resize(size, 0);
            let k = fill(&mut self.src, &mut self.buf).map_err(|e| self.io(e))?;
            self.pos += 3 + k as u64;
            if self.appended.first().is_some_and(|&next| self.pos > next) {
                // The message runs past the start of the appended data: the logger stopped
                // there, and the rest of the log continues at that offset.
                self.next_appended()?;
                continue;
            }
            if k < size {
                self.stats.truncated = true;
                self.done = true;
                continue;
            }
            let known = matches!(
                head[2],
                b'B' | b'F'
                    | b'I'
                    | b'M'
                    | b'P'
                    | b'Q'
                    | b'A'
                    | b'R'
                    | b'D'
                    | b'L'
                    | b'C'
                    | b'S'
                    | b'O'
            );
            if !known {
                // A damaged header: continue at the appended data, or at the next sync
                // marker after its first byte.
                let skipped = self
                    .appended
                    .first()
                    .map(|&next| next.saturating_sub(start));
                if self.next_appended()? {
                    self.stats.corrupt_bytes += skipped.unwrap_or(0);
                } else {
                    self.resync(start + 1)?;
                }
                continue;
            }
            return Ok(Some(head[2]));
        }
    }

    /// Moves to the next appended-data offset; false when there is none.
    fn next_appended(&mut self) -> Result<bool, UlogError> {
        if self.appended.is_empty() {
            return Ok(false);
        }
        let next = self.appended.remove(0);
        self.seek_to(next)?;
        Ok(true)
    }

    fn seek_to(&mut self, at: u64) -> Result<(), UlogError> {
        self.src.seek(SeekFrom::Start(at)).map_err(|e| self.io(e))?;
        self.pos = at;
        Ok(())
    }

    /// Skips to just after the next sync marker at or after `from` (at most
    /// [`MAX_SYNC_SEARCH`] bytes ahead); ends the stream when there is none.
    fn resync(&mut self, from: u64) -> Result<(), UlogError> {
        self.seek_to(from)?;
        let mut window: Vec<u8> = Vec::with_capacity(8);
        let mut byte = [0u8; 1];
        let limit = from.saturating_add(MAX_SYNC_SEARCH);
        while self.pos < limit {
            if fill(&mut self.src, &mut byte).map_err(|e| self.io(e))? == 0 {
                break;
            }
            self.pos += 1;
            if window.len() == 8 {
                window.remove(0);
            }
            window.push(byte[0]);
            if window == SYNC_MAGIC {
                self.stats.corrupt_bytes += self.pos - from - 8 + 1;
                return Ok(());
            }
        }
        self.stats.corrupt_bytes += self.pos.saturating_sub(from) + 1;
        self.done = true;
        Ok(())
    }

    /// The next message, `None` at the end of the log.
    pub fn next_message(&mut self) -> Result<Option<Message<'_>>, UlogError> {
        let step = loop {
            match self.step()? {
                Step::Skip => {}
                other => break other,
            }
        };
        Ok(match step {
            Step::Skip | Step::End => None,
            Step::Keyed {
                info,
                name,
                value,
                changed,
            } => {
                let name = std::str::from_utf8(&self.buf[name.0..name.1]).unwrap_or("");
                Some(if info {
                    Message::Info { key: name, value }
                } else {
                    Message::Parameter {
                        name,
                        value,
                        changed,
                    }
                })
            }
            Step::Subscribed(id) => self.subs.get(&id).map(Message::Subscribed),
            Step::Data(id) => self.subs.get(&id).map(|sub| Message::Data {
                sub,
                payload: &self.buf[2..],
            }),
            Step::Logging {
                level,
                timestamp,
                text,
            } => Some(Message::Logging {
                level,
                timestamp,
                text: std::str::from_utf8(&self.buf[text.0..text.1])
                    .unwrap_or("(not UTF-8)")
                    .trim_end_matches('\0'),
            }),
            Step::Dropout(ms) => Some(Message::Dropout { ms }),
        })
    }

    /// Reads one message and says what it is, keeping its bytes in `self.buf`.
    fn step(&mut self) -> Result<Step, UlogError> {
        let Some(kind) = self.raw()? else {
            return Ok(Step::End);
        };
        match kind {
            b'B' if self.buf.len() >= 40 => {
                let incompat = &self.buf[8..16];
                // Bit 0 of the first byte is DATA_APPENDED; any other bit is a feature
                // this reader does not know.
                let unknown = u64::from(incompat[0] & !1) << 56
                    | incompat[1..]
                        .iter()
                        .fold(0u64, |a, b| a << 8 | u64::from(*b));
                if unknown != 0 {
                    return Err(UlogError::Incompatible {
                        path: self.path.clone(),
                        flags: unknown,
                    });
                }
                if incompat[0] & 1 != 0 {
                    let mut offs: Vec<u64> = (0..3)
                        .map(|i| {
                            u64::from_le_bytes(
                                self.buf[16 + 8 * i..24 + 8 * i]
                                    .try_into()
                                    .expect("8 bytes"),
                            )
                        })
                        .filter(|&o| o > self.pos)
                        .collect();
                    offs.sort_unstable();
                    offs.dedup();
                    self.appended = offs;
                }
            }
            b'F' => {
                let text = String::from_utf8_lossy(&self.buf).into_owned();
                match split_format(&text) {
                    Some((name, fields)) => {
                        self.formats.insert(name, fields);
                    }
                    None => self.stats.bad_formats.push(shorten(&text)),
                }
            }
            b'I' | b'P' => {
                let Some(&klen) = self.buf.first() else {
                    return Ok(Step::Skip);
                };
                let klen = usize::from(klen);
                let Some(key) = self.buf.get(1..1 + klen) else {
                    return Ok(Step::Skip);
                };
                let Some(space) = key.iter().position(|b| *b == b' ') else {
                    return Ok(Step::Skip);
                };
                let ty = String::from_utf8_lossy(&key[..space]).into_owned();
                let value = InfoValue::decode(&ty, &self.buf[1 + klen..]);
                return Ok(Step::Keyed {
                    info: kind == b'I',
                    name: (1 + space + 1, 1 + klen),
                    value,
                    changed: self.in_data,
                });
            }
            b'A' => {
                self.in_data = true;
                if self.buf.len() < 4 {
                    return Ok(Step::Skip);
                }
                let multi_id = self.buf[0];
                let msg_id = u16::from_le_bytes([self.buf[1], self.buf[2]]);
                let name = String::from_utf8_lossy(&self.buf[3..])
                    .trim_end_matches('\0')
                    .to_string();
                match resolve(&name, &self.formats) {
                    Some(layout) => {
                        self.subs.insert(
                            msg_id,
                            Subscription {
                                msg_id,
                                multi_id,
                                name,
                                layout: Rc::new(layout),
                            },
                        );
                        return Ok(Step::Subscribed(msg_id));
                    }
                    None => self.stats.bad_formats.push(shorten(&name)),
                }
            }
            b'R' if self.buf.len() >= 2 => {
                self.subs
                    .remove(&u16::from_le_bytes([self.buf[0], self.buf[1]]));
            }
            b'D' => {
                self.in_data = true;
                // The logger omits a format's trailing padding, so a sample may be shorter
                // than its layout; every field read checks its own bounds.
                if self.buf.len() >= 2 + 8 {
                    let id = u16::from_le_bytes([self.buf[0], self.buf[1]]);
                    if self.subs.contains_key(&id) {
                        return Ok(Step::Data(id));
                    }
                }
                self.stats.bad_data += 1;
            }
            b'L' | b'C' => {
                let skip = if kind == b'C' { 3 } else { 1 };
                if self.buf.len() >= skip + 8 {
                    return Ok(Step::Logging {
                        level: self.buf[0],
                        timestamp: u64::from_le_bytes(
                            self.buf[skip..skip + 8].try_into().expect("8 bytes"),
                        ),
                        text: (skip + 8, self.buf.len()),
                    });
                }
            }
            b'O' if self.buf.len() >= 2 => {
                let ms = u16::from_le_bytes([self.buf[0], self.buf[1]]);
                self.stats.dropouts.0 += 1;
                self.stats.dropouts.1 += u64::from(ms);
                return Ok(Step::Dropout(ms));
            }
            // Multi-part information, default parameters and sync markers carry nothing
            // kfmc reads.
            _ => {}
        }
        Ok(Step::Skip)
    }
}

/// What one message was, its bytes left in the reader's buffer.
enum Step {
    Skip,
    End,
    Keyed {
        info: bool,
        name: (usize, usize),
        value: InfoValue,
        changed: bool,
    },
    Subscribed(u16),
    Data(u16),
    Logging {
        level: u8,
        timestamp: u64,
        text: (usize, usize),
    },
    Dropout(u16),
}

/// At most 80 characters of `s`, for a message.
fn shorten(s: &str) -> String {
    let t: String = s.chars().take(80).collect();
    if t.len() < s.len() {
        format!("{t}…")
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nested_and_array_formats_flatten_with_offsets() {
        let mut f = HashMap::new();
        f.insert(
            "inner".to_string(),
            split_format("inner:float a;uint8_t[2] b;").unwrap().1,
        );
        f.insert(
            "outer".to_string(),
            split_format("outer:uint64_t timestamp;inner[2] s;uint8_t[3] _padding0;double d;")
                .unwrap()
                .1,
        );
        let l = resolve("outer", &f).unwrap();
        let names: Vec<(&str, usize)> = l
            .fields
            .iter()
            .map(|f| (f.name.as_str(), f.offset))
            .collect();
        assert_eq!(
            names,
            [
                ("timestamp", 0),
                ("s[0].a", 8),
                ("s[0].b", 12),
                ("s[1].a", 14),
                ("s[1].b", 18),
                ("d", 23)
            ]
        );
        assert_eq!(l.size, 31);
        // A circle or an unknown type is refused, not followed.
        f.insert("loop".to_string(), split_format("loop:loop x;").unwrap().1);
        assert!(resolve("loop", &f).is_none());
        f.insert(
            "huge".to_string(),
            split_format("huge:double[100000] x;").unwrap().1,
        );
        assert!(resolve("huge", &f).is_none());
    }
}
