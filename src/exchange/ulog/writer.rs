//! A ULog writer: the logs kfmc writes itself from a simulated filter with a known S, where
//! the verdict's calibration and power are tested against known answers. It writes what PX4's
//! logger writes (header, flag bits, formats, information, parameters, subscriptions, data),
//! so that [`super::Reader`] and other ULog tools read them alike.

use std::collections::HashMap;
use std::io::Write;

use super::{FieldType, Layout, MAGIC, SYNC_MAGIC, resolve, split_format};

/// A value to encode into a field by name.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Put<'a> {
    /// One number into a scalar field (or element 0 of an array).
    Scalar(f64),
    /// Numbers into an array field's elements, in order.
    Array(&'a [f64]),
}

/// Encodes a sample of `layout` from named values; fields not named are zero. Names that the
/// layout does not have, and numbers of the wrong count, are programming errors of the
/// writer's caller.
///
/// # Panics
/// On a name the layout lacks: the caller builds its samples from the formats it declared.
pub fn encode(layout: &Layout, values: &[(&str, Put<'_>)]) -> Vec<u8> {
    let mut out = vec![0u8; layout.size];
    for (name, put) in values {
        let f = layout
            .field(name)
            .unwrap_or_else(|| panic!("format {} has no field {name}", layout.name));
        let items: &[f64] = match put {
            Put::Scalar(v) => std::slice::from_ref(v),
            Put::Array(v) => v,
        };
        for (i, v) in items.iter().take(f.count).enumerate() {
            let at = f.offset + i * f.ty.size();
            let b = &mut out[at..at + f.ty.size()];
            match f.ty {
                FieldType::I8 => b.copy_from_slice(&(*v as i8).to_le_bytes()),
                FieldType::U8 | FieldType::Char => b.copy_from_slice(&(*v as u8).to_le_bytes()),
                FieldType::Bool => b[0] = u8::from(*v != 0.0),
                FieldType::I16 => b.copy_from_slice(&(*v as i16).to_le_bytes()),
                FieldType::U16 => b.copy_from_slice(&(*v as u16).to_le_bytes()),
                FieldType::I32 => b.copy_from_slice(&(*v as i32).to_le_bytes()),
                FieldType::U32 => b.copy_from_slice(&(*v as u32).to_le_bytes()),
                FieldType::I64 => b.copy_from_slice(&(*v as i64).to_le_bytes()),
                FieldType::U64 => b.copy_from_slice(&(*v as u64).to_le_bytes()),
                FieldType::F32 => b.copy_from_slice(&(*v as f32).to_le_bytes()),
                FieldType::F64 => b.copy_from_slice(&v.to_le_bytes()),
            }
        }
    }
    out
}

/// Writes a ULog file message by message. Formats come first, then information and
/// parameters, then subscriptions and data, as PX4's logger orders them.
pub struct Writer<W: Write> {
    out: W,
    formats: HashMap<String, Vec<(String, String)>>,
    layouts: HashMap<u16, Layout>,
}

impl<W: Write> Writer<W> {
    /// Starts a log at `start_us` (µs) with the header and the flag bits (no appended data,
    /// no incompatible features).
    pub fn new(mut out: W, start_us: u64) -> std::io::Result<Self> {
        out.write_all(&MAGIC)?;
        out.write_all(&[1])?;
        out.write_all(&start_us.to_le_bytes())?;
        let mut w = Writer {
            out,
            formats: HashMap::new(),
            layouts: HashMap::new(),
        };
        w.message(b'B', &[0u8; 40])?;
        Ok(w)
    }

    fn message(&mut self, kind: u8, payload: &[u8]) -> std::io::Result<()> {
        let size = u16::try_from(payload.len()).map_err(|_| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "a ULog message holds at most 65,535 bytes",
            )
        })?;
        self.out.write_all(&size.to_le_bytes())?;
        self.out.write_all(&[kind])?;
        self.out.write_all(payload)
    }

    /// Declares a format: `text` is `name:type field;…` as PX4 writes it.
    pub fn format(&mut self, text: &str) -> std::io::Result<()> {
        let (name, fields) = split_format(text).ok_or_else(|| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "malformed format")
        })?;
        self.formats.insert(name, fields);
        self.message(b'F', text.as_bytes())
    }

    fn keyed(&mut self, kind: u8, key: &str, value: &[u8]) -> std::io::Result<()> {
        let klen = u8::try_from(key.len()).map_err(|_| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "key longer than 255")
        })?;
        let mut p = vec![klen];
        p.extend_from_slice(key.as_bytes());
        p.extend_from_slice(value);
        self.message(kind, &p)
    }

    /// An information message with a text value (`char[n] key`).
    pub fn info_text(&mut self, key: &str, value: &str) -> std::io::Result<()> {
        self.keyed(
            b'I',
            &format!("char[{}] {key}", value.len()),
            value.as_bytes(),
        )
    }

    /// An information message with a `uint32_t` value (`ver_sw_release`).
    pub fn info_u32(&mut self, key: &str, value: u32) -> std::io::Result<()> {
        self.keyed(b'I', &format!("uint32_t {key}"), &value.to_le_bytes())
    }

    /// A `float` parameter.
    pub fn param_f32(&mut self, name: &str, value: f32) -> std::io::Result<()> {
        self.keyed(b'P', &format!("float {name}"), &value.to_le_bytes())
    }

    /// An `int32_t` parameter.
    pub fn param_i32(&mut self, name: &str, value: i32) -> std::io::Result<()> {
        self.keyed(b'P', &format!("int32_t {name}"), &value.to_le_bytes())
    }

    /// Subscribes instance `multi_id` of the declared format `name` under data id `msg_id`;
    /// returns its layout.
    pub fn subscribe(&mut self, msg_id: u16, multi_id: u8, name: &str) -> std::io::Result<Layout> {
        let layout = resolve(name, &self.formats).ok_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("format {name} is not declared or does not resolve"),
            )
        })?;
        let mut p = vec![multi_id];
        p.extend_from_slice(&msg_id.to_le_bytes());
        p.extend_from_slice(name.as_bytes());
        self.message(b'A', &p)?;
        self.layouts.insert(msg_id, layout.clone());
        Ok(layout)
    }

    /// A sample of subscription `msg_id` from named values (fields not named are zero).
    ///
    /// # Panics
    /// On a subscription id that was not subscribed, or a name its format lacks.
    pub fn data(&mut self, msg_id: u16, values: &[(&str, Put<'_>)]) -> std::io::Result<()> {
        let layout = self
            .layouts
            .get(&msg_id)
            .unwrap_or_else(|| panic!("msg_id {msg_id} was not subscribed"));
        let mut p = msg_id.to_le_bytes().to_vec();
        p.extend_from_slice(&encode(layout, values));
        self.message(b'D', &p)
    }

    /// A text message at syslog `level` (`b'6'` is info).
    pub fn logging(&mut self, level: u8, timestamp: u64, text: &str) -> std::io::Result<()> {
        let mut p = vec![level];
        p.extend_from_slice(&timestamp.to_le_bytes());
        p.extend_from_slice(text.as_bytes());
        self.message(b'L', &p)
    }

    /// A sync marker.
    pub fn sync(&mut self) -> std::io::Result<()> {
        self.message(b'S', &SYNC_MAGIC)
    }

    /// Flushes and returns the output.
    pub fn finish(mut self) -> std::io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}
