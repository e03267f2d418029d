//! JSON input read strictly: a key given twice in one object is an error naming it (serde_json
//! keeps the last of two: `"fl_x": 500, …, "fl_x": 800` would be a camera of 800 pixels with
//! nothing said, and a file written by hand or merged by a script is where that happens), and so
//! is a number that f32 would make 0 or infinite.

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

/// Refuses a number of `value` that f32 would make 0 or infinite (`exact::float_within_f32`),
/// naming its path below `path` (as `light[0].radiance[1]`).
pub fn within_f32(value: &Value, path: &str) -> anyhow::Result<()> {
    let child = |key: &str| match path {
        "" => key.to_string(),
        parent => format!("{parent}.{key}"),
    };
    match value {
        Value::Number(n) => n
            .as_f64()
            .map_or(Ok(()), |x| crate::io::exact::float_within_f32(path, x)),
        Value::Array(items) => (items.iter().enumerate())
            .try_for_each(|(i, item)| within_f32(item, &format!("{path}[{i}]"))),
        Value::Object(object) => object
            .iter()
            .try_for_each(|(k, v)| within_f32(v, &child(k))),
        _ => Ok(()),
    }
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

    #[test]
    fn numbers_beyond_f32_are_named_by_their_path() {
        let ok = serde_json::json!({"a": [0.0, 3e38, -1e-30, 7], "b": {"c": "x"}});
        within_f32(&ok, "").unwrap();
        let bad = serde_json::json!({"light": [{"radiance": [1.0, 1e-300]}]});
        let error = within_f32(&bad, "").unwrap_err().to_string();
        assert!(error.contains("light[0].radiance[1] = 1e-300"), "{error}");
    }
}
