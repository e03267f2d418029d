//! Fixed-length arrays in files (a position's `[x, y, z]`), refused when they hold more values
//! than their length: serde's arrays stop reading at their length and let the rest go unread, so
//! `[0, 0, 12, 1]` would be taken for `[0, 0, 12]`.
//!
//! `#[serde(deserialize_with = "exact::array")]` on an `[T; N]` field, `exact::optional_array`
//! on an `Option<[T; N]>`.

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
