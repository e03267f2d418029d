//! Values in files read exactly as written, or refused.
//!
//! Fixed-length arrays (a position's `[x, y, z]`) are refused when they hold more values than
//! their length: serde's arrays stop reading at their length and let the rest go unread, so
//! `[0, 0, 12, 1]` would be taken for `[0, 0, 12]`. `#[serde(deserialize_with = "exact::array")]`
//! on an `[T; N]` field, `exact::optional_array` on an `Option<[T; N]>`.
//!
//! Numbers beyond f32's range (`within_f32`): serde reads a TOML float into an f32 field by a cast,
//! so `density_scale = 1e-46` would be an empty medium and `fov_deg = 1e300` a check's "got inf".

use serde::de::{Deserialize, Deserializer, Error};

/// An array of exactly `N` values.
pub fn array<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    exactly(Vec::<T>::deserialize(d)?)
}

/// `array` for an optional field.
pub fn optional_array<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    Option::<Vec<T>>::deserialize(d)?.map(exactly).transpose()
}

/// Refuses `x`, the value of `key`, if it is not 0 but would be 0 or infinite as an f32.
pub fn float_within_f32(key: &str, x: f64) -> anyhow::Result<()> {
    let narrowed = x as f32;
    if x.is_finite() && (narrowed.is_infinite() || (narrowed == 0.0) != (x == 0.0)) {
        anyhow::bail!("{key} = {x:e} is beyond a 32-bit float's range (about 1e-45 to 3e38 in magnitude), which volgrad computes in");
    }
    Ok(())
}

/// Refuses a float of the TOML `text` (already parsed once, so it is valid TOML) that is not 0
/// but would be 0 or infinite as an f32, naming its key: volgrad computes in f32, and a key read as
/// f64 holds values far inside that range anyway (positions within ±1e15).
pub fn within_f32(text: &str) -> anyhow::Result<()> {
    fn walk(value: &toml::Value, key: &str) -> anyhow::Result<()> {
        match value {
            toml::Value::Float(x) => float_within_f32(key, *x),
            toml::Value::Array(items) => (items.iter().enumerate())
                .try_for_each(|(i, item)| walk(item, &format!("{key}[{i}]"))),
            toml::Value::Table(table) => table.iter().try_for_each(|(k, v)| {
                walk(
                    v,
                    &if key.is_empty() {
                        k.clone()
                    } else {
                        format!("{key}.{k}")
                    },
                )
            }),
            _ => Ok(()),
        }
    }
    walk(&toml::Value::Table(toml::from_str(text)?), "")
}

fn exactly<E: Error, T, const N: usize>(values: Vec<T>) -> Result<[T; N], E> {
    let got = values.len();
    values
        .try_into()
        .map_err(|_| E::invalid_length(got, &format!("an array of {N} numbers").as_str()))
}

#[cfg(test)]
mod tests {
    #[derive(serde::Deserialize, Debug)]
    struct Camera {
        #[serde(deserialize_with = "super::array")]
        position: [f32; 3],
        #[serde(default, deserialize_with = "super::optional_array")]
        offset: Option<[f64; 3]>,
    }

    #[test]
    fn numbers_beyond_f32_are_refused_by_key() {
        assert!(super::within_f32("a = 0.0\nb = -1e-30\nc = [3e38, 1]\nd = nan\ne = inf").is_ok());
        for (bad, key) in [
            (
                "[medium]\ndensity_scale = 1e-46",
                "medium.density_scale = 1e-46",
            ),
            ("x = [1, -1e300]", "x[1] = -1e300"),
            (
                "[[light]]\nradiance = [1e39, 0, 0]",
                "light[0].radiance[0] = 1e39",
            ),
        ] {
            let err = super::within_f32(bad).unwrap_err().to_string();
            assert!(err.contains(key) && err.contains("32-bit"), "{bad}: {err}");
        }
    }

    #[test]
    fn arrays_of_another_length_are_refused() {
        let read = |text: &str| toml::from_str::<Camera>(text);
        let c = read("position = [0, 0, 12]\noffset = [1, 2, 3]").unwrap();
        assert_eq!(
            (c.position, c.offset),
            ([0.0, 0.0, 12.0], Some([1.0, 2.0, 3.0]))
        );
        assert_eq!(read("position = [0, 0, 12]").unwrap().offset, None);
        for bad in [
            "position = [0, 0, 12, 1]",
            "position = [0, 0]",
            "position = [0, 0, 1]\noffset = [1, 2, 3, 4]",
        ] {
            let err = read(bad).unwrap_err().to_string();
            assert!(err.contains("an array of 3 numbers"), "{bad}: {err}");
        }
    }
}
