//! Refusing non-finite numbers before they are written as JSON (which has
//! no NaN or infinity: `serde_json` would write `null`, which no reader of
//! the formats accepts as a number).

use std::fmt::{self, Display};
use std::path::PathBuf;

use serde::ser::{self, Serialize};

use crate::error::{Error, Result};

/// Errors ([`Error::Format`] naming `path`, the file the value is about to
/// be written to, and the field, e.g. `contacts[1].fz_n`) if `value` holds
/// a NaN or infinite `f32` or `f64` anywhere.
pub fn check_finite<T: Serialize + ?Sized>(value: &T, path: impl Into<PathBuf>) -> Result<()> {
    let mut checker = Checker { at: Vec::new() };
    match value.serialize(&mut checker) {
        Ok(()) => Ok(()),
        Err(Found::NonFinite(field, x)) => Err(Error::format(
            path,
            None,
            format!(
                "refusing to write {x} at `{}`: JSON has no NaN or infinity",
                if field.is_empty() {
                    "(top level)"
                } else {
                    &field
                }
            ),
        )),
        Err(Found::Other(m)) => Err(Error::format(path, None, format!("cannot serialize: {m}"))),
    }
}

/// Why the walk stopped.
#[derive(Debug)]
enum Found {
    /// The field path and the value.
    NonFinite(String, f64),
    /// The value's own `Serialize` failed.
    Other(String),
}

impl Display for Found {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Found::NonFinite(p, x) => write!(f, "{x} at {p}"),
            Found::Other(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for Found {}

impl ser::Error for Found {
    fn custom<M: Display>(msg: M) -> Self {
        Found::Other(msg.to_string())
    }
}

/// A serializer that writes nothing and stops at the first non-finite
/// number, keeping the path of fields and indices that leads to it.
struct Checker {
    at: Vec<String>,
}

impl Checker {
    fn path(&self) -> String {
        let mut s = String::new();
        for part in &self.at {
            if !part.starts_with('[') && !s.is_empty() {
                s.push('.');
            }
            s.push_str(part);
        }
        s
    }

    fn float(&self, x: f64) -> Result<(), Found> {
        if x.is_finite() {
            Ok(())
        } else {
            Err(Found::NonFinite(self.path(), x))
        }
    }

    fn nested<T: Serialize + ?Sized>(&mut self, part: String, value: &T) -> Result<(), Found> {
        self.at.push(part);
        let r = value.serialize(&mut *self);
        self.at.pop();
        r
    }
}

/// A sequence, tuple, map or struct being walked: the serializer and the
/// index of the next element.
struct Compound<'a> {
    c: &'a mut Checker,
    index: usize,
}

impl Compound<'_> {
    fn element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        let part = format!("[{}]", self.index);
        self.index += 1;
        self.c.nested(part, value)
    }
}

macro_rules! ok {
    ($($name:ident($($t:ty),*);)*) => {
        $(fn $name(self, $(_: $t),*) -> Result<(), Found> { Ok(()) })*
    };
}

impl<'a> ser::Serializer for &'a mut Checker {
    type Ok = ();
    type Error = Found;
    type SerializeSeq = Compound<'a>;
    type SerializeTuple = Compound<'a>;
    type SerializeTupleStruct = Compound<'a>;
    type SerializeTupleVariant = Compound<'a>;
    type SerializeMap = Compound<'a>;
    type SerializeStruct = Compound<'a>;
    type SerializeStructVariant = Compound<'a>;

    ok! {
        serialize_bool(bool);
        serialize_i8(i8);
        serialize_i16(i16);
        serialize_i32(i32);
        serialize_i64(i64);
        serialize_i128(i128);
        serialize_u8(u8);
        serialize_u16(u16);
        serialize_u32(u32);
        serialize_u64(u64);
        serialize_u128(u128);
        serialize_char(char);
        serialize_str(&str);
        serialize_bytes(&[u8]);
        serialize_none();
        serialize_unit();
        serialize_unit_struct(&'static str);
        serialize_unit_variant(&'static str, u32, &'static str);
    }

    fn serialize_f32(self, v: f32) -> Result<(), Found> {
        self.float(f64::from(v))
    }
    fn serialize_f64(self, v: f64) -> Result<(), Found> {
        self.float(v)
    }
    fn serialize_some<T: Serialize + ?Sized>(self, value: &T) -> Result<(), Found> {
        value.serialize(self)
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        value: &T,
    ) -> Result<(), Found> {
        value.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        value: &T,
    ) -> Result<(), Found> {
        self.nested(variant.to_string(), value)
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_tuple(self, _: usize) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Compound<'a>, Found> {
        Ok(Compound { c: self, index: 0 })
    }
}

impl ser::SerializeSeq for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        self.element(value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeTuple for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_element<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        self.element(value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeTupleStruct for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        self.element(value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeTupleVariant for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_field<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        self.element(value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeMap for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> Result<(), Found> {
        key.serialize(&mut *self.c)
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, value: &T) -> Result<(), Found> {
        self.element(value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeStruct for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_field<T: Serialize + ?Sized>(
        &mut self,
        key: &'static str,
        value: &T,
    ) -> Result<(), Found> {
        self.c.nested(key.to_string(), value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

impl ser::SerializeStructVariant for Compound<'_> {
    type Ok = ();
    type Error = Found;
    fn serialize_field<T: Serialize + ?Sized>(
        &mut self,
        key: &'static str,
        value: &T,
    ) -> Result<(), Found> {
        self.c.nested(key.to_string(), value)
    }
    fn end(self) -> Result<(), Found> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{ContactRecord, FrameRecord};

    #[test]
    fn names_the_field_of_a_non_finite_number() {
        let mut rec = FrameRecord {
            frame: "a.png".into(),
            t_s: 0.5,
            contacts: vec![ContactRecord::default(), ContactRecord::default()],
            latency_ms: None,
        };
        check_finite(&rec, "c.jsonl").unwrap();
        rec.contacts[1].fz_n = f64::INFINITY;
        let e = check_finite(&rec, "c.jsonl").unwrap_err().to_string();
        assert!(
            e.contains("c.jsonl") && e.contains("`contacts[1].fz_n`"),
            "{e}"
        );
        rec.contacts[1].fz_n = 0.0;
        rec.latency_ms = Some(f64::NAN);
        let e = check_finite(&rec, "c.jsonl").unwrap_err().to_string();
        assert!(e.contains("NaN at `latency_ms`"), "{e}");
        let map: std::collections::BTreeMap<&str, Vec<f32>> = [("k", vec![1.0, f32::NAN])].into();
        let e = check_finite(&map, "m.json").unwrap_err().to_string();
        assert!(e.contains("`[0][1]`"), "{e}");
    }
}
