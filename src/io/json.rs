//! JSON input read strictly: a key given twice in one object is an error naming it. serde_json
//! keeps the last of two (`"fl_x": 500, …, "fl_x": 800` would be a camera of 800 pixels with
//! nothing said), and a file written by hand or merged by a script is where that happens.

use std::fmt;

use serde::de::{DeserializeSeed, Error, MapAccess, SeqAccess, Visitor};
use serde_json::{Map, Value};

/// `text` as a JSON value, refusing a repeated key (by its path, as `frames[3].fl_x`).
pub fn parse(text: &str) -> serde_json::Result<Value> {
    let mut deserializer = serde_json::Deserializer::from_str(text);
    let value = Checked {
        path: String::new(),
    }
    .deserialize(&mut deserializer)?;
    deserializer.end()?;
    Ok(value)
}

/// A value at `path` (empty at the top), its objects checked for repeated keys.
struct Checked {
    path: String,
}

impl<'de> DeserializeSeed<'de> for Checked {
    type Value = Value;

    fn deserialize<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<Value, D::Error> {
        deserializer.deserialize_any(self)
    }
}

impl<'de> Visitor<'de> for Checked {
    type Value = Value;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a JSON value")
    }

    fn visit_bool<E>(self, v: bool) -> Result<Value, E> {
        Ok(Value::Bool(v))
    }

    fn visit_i64<E>(self, v: i64) -> Result<Value, E> {
        Ok(Value::from(v))
    }

    fn visit_u64<E>(self, v: u64) -> Result<Value, E> {
        Ok(Value::from(v))
    }

    fn visit_f64<E>(self, v: f64) -> Result<Value, E> {
        Ok(Value::from(v))
    }

    fn visit_str<E>(self, v: &str) -> Result<Value, E> {
        Ok(Value::String(v.to_owned()))
    }

    fn visit_unit<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut items: A) -> Result<Value, A::Error> {
        let mut values = Vec::new();
        loop {
            let path = format!("{}[{}]", self.path, values.len());
            match items.next_element_seed(Checked { path })? {
                Some(value) => values.push(value),
                None => return Ok(Value::Array(values)),
            }
        }
    }

    fn visit_map<A: MapAccess<'de>>(self, mut entries: A) -> Result<Value, A::Error> {
        let mut object = Map::new();
        while let Some(key) = entries.next_key::<String>()? {
            let path = match self.path.as_str() {
                "" => key.clone(),
                parent => format!("{parent}.{key}"),
            };
            let value = entries.next_value_seed(Checked { path: path.clone() })?;
            if object.insert(key, value).is_some() {
                return Err(A::Error::custom(format!(
                    "the key \"{path}\" is given twice (which one is meant?)"
                )));
            }
        }
        Ok(Value::Object(object))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_repeated_key_is_named_by_its_path() {
        let value = parse(r#"{"a": [1, {"b": 2.5, "c": null}], "d": "x"}"#).unwrap();
        assert_eq!(
            value,
            serde_json::json!({"a": [1, {"b": 2.5, "c": null}], "d": "x"})
        );
        let error = parse(r#"{"a": [1, {"b": 2, "b": 3}]}"#)
            .unwrap_err()
            .to_string();
        assert!(error.contains("\"a[1].b\" is given twice"), "{error}");
        let error = parse("{\"fl_x\": 500,\n \"fl_x\": 800}")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("\"fl_x\" is given twice") && error.contains("line 2"),
            "{error}"
        );
        assert!(parse("{} {}").is_err(), "trailing characters");
    }
}
