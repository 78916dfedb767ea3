//! A serde `Deserializer` over Python objects ([`PyDe`]), so that the
//! binding reads the parameter dict into the core's types through their
//! serde derives (`hybridmpm-mpm`'s `serde` feature): the keys, the defaults
//! of missing keys and the refusal of unknown keys are the core's, written
//! once. (pythonize would do the reading, but no release of it supports
//! pyo3 0.30.) It is strict as the binding always was: a number is an `int`
//! or `float` (numpy scalars included), never a bool or a string; an integer
//! is an `int`, never a float; a list is any sequence but a string; a dict
//! key whose value is `None` is a missing key; an enum is a string naming a
//! unit variant (`"sticky"`) or a dict of one key naming a variant with
//! data, its value the data (`{"elastic": {...}}`). Every error names the
//! field by its path (`water.density`, `walls.faces.y-.friction`,
//! `colliders[0].center`, `sets[2]`).

use std::fmt;

use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use serde::de::{self, DeserializeOwned, DeserializeSeed, Visitor};
use serde::forward_to_deserialize_any;

use crate::errors::{invalid_input, repr};

/// A parameter that cannot be read: the field it belongs to (its path from
/// the root, once known) and what is wrong with it.
#[derive(Debug)]
pub struct Error {
    field: Option<String>,
    /// A missing field, named under the path the error gets.
    missing: Option<&'static str>,
    /// The fields allowed where an unknown one was found.
    allowed: Option<Vec<&'static str>>,
    msg: String,
}

impl Error {
    fn new(field: Option<String>, msg: String) -> Self {
        Error {
            field,
            missing: None,
            allowed: None,
            msg,
        }
    }

    /// Gives the error the path `path` unless a deeper one named it already.
    fn at(mut self, path: &str) -> Self {
        if self.field.is_none() {
            self.field = Some(match self.missing.take() {
                Some(key) => join(path, key),
                None => path.to_string(),
            });
        }
        self
    }

    /// Adds `before` and `after` to the allowed keys of an unknown key at the
    /// root (the keys a caller reads apart from the deserialised struct).
    pub fn with_root_keys(mut self, before: &[&'static str], after: &[&'static str]) -> Self {
        let at_root = self
            .field
            .as_deref()
            .is_some_and(|f| !f.contains(['.', '[']));
        if let (true, Some(allowed)) = (at_root, self.allowed.as_mut()) {
            *allowed = [before, allowed.as_slice(), after].concat();
        }
        self
    }

    /// `InvalidInputError` naming the field.
    pub fn into_py(self, py: Python<'_>) -> PyErr {
        let msg = match &self.allowed {
            Some(allowed) => format!("unknown parameter (allowed: {})", allowed.join(", ")),
            None => self.msg,
        };
        invalid_input(py, self.field.as_deref().unwrap_or("params"), msg)
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.field.as_deref().unwrap_or("?"), self.msg)
    }
}

impl std::error::Error for Error {}

impl de::Error for Error {
    fn custom<T: fmt::Display>(msg: T) -> Self {
        Error::new(None, msg.to_string())
    }

    fn invalid_length(len: usize, exp: &dyn de::Expected) -> Self {
        Error::new(None, format!("expected {exp}, got {len}"))
    }

    fn unknown_variant(variant: &str, expected: &'static [&'static str]) -> Self {
        let names: Vec<String> = expected.iter().map(|v| format!("'{v}'")).collect();
        Error::new(
            None,
            format!("must be one of {}, got '{variant}'", names.join(", ")),
        )
    }

    fn unknown_field(field: &str, expected: &'static [&'static str]) -> Self {
        let mut e = Error::new(None, format!("unknown parameter '{field}'"));
        e.allowed = Some(expected.to_vec());
        e
    }

    fn missing_field(field: &'static str) -> Self {
        let mut e = Error::new(None, "missing".into());
        e.missing = Some(field);
        e
    }
}

fn join(path: &str, key: &str) -> String {
    if path.is_empty() {
        key.to_string()
    } else {
        format!("{path}.{key}")
    }
}

/// Reads a `T` from `obj`, naming fields under `path` (`""` at the root).
pub fn read<T: DeserializeOwned>(obj: &Bound<'_, PyAny>, path: &str) -> Result<T, Error> {
    T::deserialize(PyDe::new(obj.clone(), path.to_string())).map_err(|e| e.at(path))
}

// ---------------------------------------------------------------- deserializer

/// A dict entry: key and value.
type Entry<'py> = (Bound<'py, PyAny>, Bound<'py, PyAny>);

/// A Python object being read at field path `path`.
struct PyDe<'py> {
    obj: Bound<'py, PyAny>,
    path: String,
    /// The value of an `Option` (error messages add "or None").
    optional: bool,
}

impl<'py> PyDe<'py> {
    fn new(obj: Bound<'py, PyAny>, path: String) -> Self {
        PyDe {
            obj,
            path,
            optional: false,
        }
    }

    fn expected(&self, what: &str) -> Error {
        let none = if self.optional { " or None" } else { "" };
        Error::new(
            Some(self.path.clone()),
            format!("expected {what}{none}, got {}", repr(&self.obj)),
        )
    }

    fn is_bool(&self) -> bool {
        self.obj.is_instance_of::<PyBool>()
    }

    fn number(&self) -> Result<f64, Error> {
        if self.is_bool() {
            return Err(self.expected("a number"));
        }
        self.obj
            .extract::<f64>()
            .map_err(|_| self.expected("a number"))
    }

    fn string(&self) -> Result<String, Error> {
        match self.obj.cast::<PyString>() {
            Ok(s) => Ok(s.to_string()),
            Err(_) => Err(self.expected("a string")),
        }
    }

    /// The items of a list, tuple or other sequence (not a string), as
    /// pyo3 reads a `Vec`.
    fn items(&self) -> Result<Vec<Bound<'py, PyAny>>, Error> {
        if self.obj.is_instance_of::<PyDict>() {
            return Err(self.expected("a list"));
        }
        self.obj
            .extract::<Vec<Bound<'py, PyAny>>>()
            .map_err(|_| self.expected("a list"))
    }

    fn entries(&self) -> Result<Vec<Entry<'py>>, Error> {
        let d = self
            .obj
            .cast::<PyDict>()
            .map_err(|_| self.expected("a dict"))?;
        Ok(d.iter().collect())
    }

    fn map<'de, V: Visitor<'de>>(
        self,
        visitor: V,
        fields: Option<&'static [&'static str]>,
    ) -> Result<V::Value, Error> {
        let entries = self.entries()?;
        visitor
            .visit_map(DictAccess {
                entries: entries.into_iter(),
                value: None,
                path: &self.path,
                fields,
            })
            .map_err(|e: Error| e.at(&self.path))
    }
}

macro_rules! unsigned {
    ($($method:ident => $ty:ty, $visit:ident;)*) => {$(
        fn $method<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
            let what = "a non-negative integer";
            if self.is_bool() {
                return Err(self.expected(what));
            }
            let x = self.obj.extract::<$ty>().map_err(|_| self.expected(what))?;
            visitor.$visit(x).map_err(|e: Error| e.at(&self.path))
        }
    )*};
}

macro_rules! signed {
    ($($method:ident => $ty:ty, $visit:ident;)*) => {$(
        fn $method<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
            let what = "an integer";
            if self.is_bool() {
                return Err(self.expected(what));
            }
            let x = self.obj.extract::<$ty>().map_err(|_| self.expected(what))?;
            visitor.$visit(x).map_err(|e: Error| e.at(&self.path))
        }
    )*};
}

impl<'de, 'py> de::Deserializer<'de> for PyDe<'py> {
    type Error = Error;

    fn deserialize_any<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let o = &self.obj;
        if o.is_none() {
            return visitor.visit_unit().map_err(|e: Error| e.at(&self.path));
        }
        if self.is_bool() {
            return self.deserialize_bool(visitor);
        }
        if o.is_instance_of::<PyInt>() {
            return match o.extract::<u64>() {
                Ok(_) => self.deserialize_u64(visitor),
                Err(_) => self.deserialize_i64(visitor),
            };
        }
        if o.is_instance_of::<PyFloat>() {
            return self.deserialize_f64(visitor);
        }
        if o.is_instance_of::<PyString>() {
            return self.deserialize_string(visitor);
        }
        if o.is_instance_of::<PyDict>() {
            return self.deserialize_map(visitor);
        }
        if o.is_instance_of::<PyList>() || o.is_instance_of::<PyTuple>() {
            return self.deserialize_seq(visitor);
        }
        Err(self.expected("a number, a string, a list or a dict"))
    }

    fn deserialize_bool<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let b = self
            .obj
            .cast::<PyBool>()
            .map_err(|_| self.expected("True or False"))?
            .is_true();
        visitor.visit_bool(b).map_err(|e: Error| e.at(&self.path))
    }

    unsigned! {
        deserialize_u8 => u8, visit_u8;
        deserialize_u16 => u16, visit_u16;
        deserialize_u32 => u32, visit_u32;
        deserialize_u64 => u64, visit_u64;
    }

    signed! {
        deserialize_i8 => i8, visit_i8;
        deserialize_i16 => i16, visit_i16;
        deserialize_i32 => i32, visit_i32;
        deserialize_i64 => i64, visit_i64;
    }

    fn deserialize_f32<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let x = self.number()?;
        visitor
            .visit_f32(x as f32)
            .map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_f64<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let x = self.number()?;
        visitor.visit_f64(x).map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_char<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_string(visitor)
    }

    fn deserialize_str<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_string(visitor)
    }

    fn deserialize_string<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let s = self.string()?;
        visitor.visit_string(s).map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_bytes<V: Visitor<'de>>(self, _visitor: V) -> Result<V::Value, Error> {
        Err(self.expected("bytes"))
    }

    fn deserialize_byte_buf<V: Visitor<'de>>(self, _visitor: V) -> Result<V::Value, Error> {
        Err(self.expected("bytes"))
    }

    fn deserialize_option<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        if self.obj.is_none() {
            return visitor.visit_none().map_err(|e: Error| e.at(&self.path));
        }
        let path = self.path.clone();
        visitor
            .visit_some(PyDe {
                optional: true,
                ..self
            })
            .map_err(|e: Error| e.at(&path))
    }

    fn deserialize_unit<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        if !self.obj.is_none() {
            return Err(self.expected("None"));
        }
        visitor.visit_unit().map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_unit_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        visitor: V,
    ) -> Result<V::Value, Error> {
        self.deserialize_unit(visitor)
    }

    fn deserialize_newtype_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        visitor: V,
    ) -> Result<V::Value, Error> {
        let path = self.path.clone();
        visitor
            .visit_newtype_struct(self)
            .map_err(|e: Error| e.at(&path))
    }

    fn deserialize_seq<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        let items = self.items()?;
        visitor
            .visit_seq(ListAccess {
                items: items.into_iter().enumerate(),
                path: &self.path,
            })
            .map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_tuple<V: Visitor<'de>>(
        self,
        _len: usize,
        visitor: V,
    ) -> Result<V::Value, Error> {
        self.deserialize_seq(visitor)
    }

    fn deserialize_tuple_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        _len: usize,
        visitor: V,
    ) -> Result<V::Value, Error> {
        self.deserialize_seq(visitor)
    }

    fn deserialize_map<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.map(visitor, None)
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Error> {
        self.map(visitor, Some(fields))
    }

    /// An enum in serde's externally tagged form: a string names a unit
    /// variant (`"sticky"`, `"box"`); a dict of one key names a variant
    /// with data, the key's value its data (`{"elastic": {...}}`, read at
    /// `path.elastic`). Anything else, and a dict of no key or several, is
    /// refused at `path`, listing the variants.
    fn deserialize_enum<V: Visitor<'de>>(
        self,
        _name: &'static str,
        variants: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Error> {
        let quoted: Vec<String> = variants.iter().map(|v| format!("'{v}'")).collect();
        let names = quoted.join(", ");
        let (name, value) = if let Ok(d) = self.obj.cast::<PyDict>() {
            let mut entries: Vec<Entry<'py>> = d.iter().collect();
            if entries.len() != 1 {
                let keys: Vec<String> = entries.iter().map(|(k, _)| repr(k)).collect();
                let got = match keys.len() {
                    0 => "an empty dict".to_string(),
                    n => format!("{n} keys: {}", keys.join(", ")),
                };
                return Err(Error::new(
                    Some(self.path),
                    format!("expected a dict naming exactly one of {names}, got {got}"),
                ));
            }
            let (key, value) = entries.pop().expect("one entry");
            let Ok(name) = key.cast::<PyString>().map(|k| k.to_string()) else {
                return Err(Error::new(
                    Some(self.path),
                    format!("keys must be strings, got {}", repr(&key)),
                ));
            };
            (name, Some(value))
        } else if self.obj.is_instance_of::<PyString>() {
            (self.string()?, None)
        } else {
            return Err(self.expected(&format!("one of {names}")));
        };
        let path = self.path.clone();
        visitor
            .visit_enum(VariantDe { name, value, path })
            .map_err(|e: Error| e.at(&self.path))
    }

    fn deserialize_identifier<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_string(visitor)
    }

    fn deserialize_ignored_any<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_unit()
    }
}

/// The items of a list, each read at `path[i]`.
struct ListAccess<'a, 'py> {
    items: std::iter::Enumerate<std::vec::IntoIter<Bound<'py, PyAny>>>,
    path: &'a str,
}

impl<'de> de::SeqAccess<'de> for ListAccess<'_, '_> {
    type Error = Error;

    fn next_element_seed<T: DeserializeSeed<'de>>(
        &mut self,
        seed: T,
    ) -> Result<Option<T::Value>, Error> {
        match self.items.next() {
            None => Ok(None),
            Some((i, item)) => {
                let path = format!("{}[{i}]", self.path);
                seed.deserialize(PyDe::new(item, path.clone()))
                    .map(Some)
                    .map_err(|e| e.at(&path))
            }
        }
    }

    fn size_hint(&self) -> Option<usize> {
        Some(self.items.len())
    }
}

/// The entries of a dict, each value read at `path.key`. For a struct
/// (`fields` given), a known key whose value is `None` is left out: it takes
/// its default like a missing key.
struct DictAccess<'a, 'py> {
    entries: std::vec::IntoIter<Entry<'py>>,
    value: Option<(String, Bound<'py, PyAny>)>,
    path: &'a str,
    fields: Option<&'static [&'static str]>,
}

impl<'de> de::MapAccess<'de> for DictAccess<'_, '_> {
    type Error = Error;

    fn next_key_seed<K: DeserializeSeed<'de>>(
        &mut self,
        seed: K,
    ) -> Result<Option<K::Value>, Error> {
        for (key, value) in self.entries.by_ref() {
            let Ok(key) = key.cast::<PyString>().map(|k| k.to_string()) else {
                return Err(Error::new(
                    Some(self.path.to_string()),
                    format!("keys must be strings, got {}", repr(&key)),
                ));
            };
            if value.is_none() && self.fields.is_some_and(|f| f.contains(&key.as_str())) {
                continue;
            }
            let path = join(self.path, &key);
            let k = seed.deserialize(NameDe {
                name: key,
                path: path.clone(),
            })?;
            self.value = Some((path, value));
            return Ok(Some(k));
        }
        Ok(None)
    }

    fn next_value_seed<T: DeserializeSeed<'de>>(&mut self, seed: T) -> Result<T::Value, Error> {
        let (path, value) = self
            .value
            .take()
            .ok_or_else(|| Error::new(Some(self.path.to_string()), "a value without key".into()))?;
        // `at` again: a `Deserialize` impl may fail after reading the value
        // (a list of the wrong length), outside the value's deserializer.
        seed.deserialize(PyDe::new(value, path.clone()))
            .map_err(|e| e.at(&path))
    }

    fn size_hint(&self) -> Option<usize> {
        Some(self.entries.len())
    }
}

/// A name (a dict key, an enum variant) read at `path`: its errors (an
/// unknown field or variant) name that path.
struct NameDe {
    name: String,
    path: String,
}

impl<'de> de::Deserializer<'de> for NameDe {
    type Error = Error;

    fn deserialize_any<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor
            .visit_string(self.name)
            .map_err(|e: Error| e.at(&self.path))
    }

    forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string
        bytes byte_buf option unit unit_struct newtype_struct seq tuple
        tuple_struct map struct enum identifier ignored_any
    }
}

/// The variant an enum's value names (`name`, read at `path`) and, in the
/// dict form, the data under it (read at `path.name`).
struct VariantDe<'py> {
    name: String,
    value: Option<Bound<'py, PyAny>>,
    path: String,
}

impl<'py> VariantDe<'py> {
    /// The data of a variant that has some: the dict form's value.
    fn data(self) -> Result<PyDe<'py>, Error> {
        match self.value {
            Some(v) => Ok(PyDe::new(v, join(&self.path, &self.name))),
            None => Err(Error::new(
                Some(self.path),
                format!(
                    "'{0}' takes parameters: expected a dict {{'{0}': {{...}}}}, got '{0}'",
                    self.name
                ),
            )),
        }
    }
}

impl<'de, 'py> de::EnumAccess<'de> for VariantDe<'py> {
    type Error = Error;
    type Variant = Self;

    fn variant_seed<T: DeserializeSeed<'de>>(self, seed: T) -> Result<(T::Value, Self), Error> {
        let v = seed.deserialize(NameDe {
            name: self.name.clone(),
            path: self.path.clone(),
        })?;
        Ok((v, self))
    }
}

impl<'de, 'py> de::VariantAccess<'de> for VariantDe<'py> {
    type Error = Error;

    fn unit_variant(self) -> Result<(), Error> {
        match self.value {
            None => Ok(()),
            Some(_) => Err(Error::new(
                Some(self.path),
                format!("expected the name '{}' alone, not a dict", self.name),
            )),
        }
    }

    fn newtype_variant_seed<T: DeserializeSeed<'de>>(self, seed: T) -> Result<T::Value, Error> {
        let de = self.data()?;
        let path = de.path.clone();
        seed.deserialize(de).map_err(|e| e.at(&path))
    }

    fn tuple_variant<V: Visitor<'de>>(self, _len: usize, visitor: V) -> Result<V::Value, Error> {
        de::Deserializer::deserialize_seq(self.data()?, visitor)
    }

    fn struct_variant<V: Visitor<'de>>(
        self,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Error> {
        self.data()?.map(visitor, Some(fields))
    }
}
