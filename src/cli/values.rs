//! The hand-written value formats of the command line: durations ("120s", "2m"), inclusive index
//! boxes ("x0,y0,z0,x1,y1,z1" or "all"), voxel lists ("x,y,z;x,y,z") and `--fd` directions.

use std::time::Duration;

use anyhow::{bail, Context, Result};
use glam::IVec3;

/// The longest duration a flag takes: further than any run, and short enough that the clock it
/// is added to cannot overflow.
const MAX_SECONDS: f64 = 1e9;

/// "120s", "2m", "1.5h", "250ms", "90" (seconds).
pub fn duration(text: &str) -> Result<Duration, String> {
    let t = text.trim();
    // The unit is the trailing letters, so that a number may have an exponent ("1e-3s").
    let (number, unit) = match t.trim_end_matches(|c: char| c.is_ascii_alphabetic()).len() {
        i if i == t.len() => (t, "s"),
        i => t.split_at(i),
    };
    let factor = match unit {
        "ms" => 1e-3,
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => {
            return Err(format!(
                "unknown unit '{unit}' in '{text}' (use ms, s, m, min or h, e.g. 120s)"
            ))
        }
    };
    match number.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 && v * factor <= MAX_SECONDS => {
            match Duration::from_secs_f64(v * factor) {
                // Not rounded to 0, which a budget would refuse as "must be above 0".
                d if d.is_zero() && v > 0.0 => Err(format!(
                    "'{text}' is shorter than a nanosecond, the clock's resolution"
                )),
                d => Ok(d),
            }
        }
        Ok(v) if v * factor > MAX_SECONDS => Err(format!(
            "'{text}' is too long a duration (at most {MAX_SECONDS:e} s, about 30 years)"
        )),
        _ => Err(format!("'{text}' is not a duration (e.g. 120s, 2m)")),
    }
}

/// Comma-separated integers; `what` names the flag in the error.
fn integers(text: &str, what: &str) -> Result<Vec<i32>> {
    text.split(',')
        .map(|x| {
            x.trim()
                .parse::<i32>()
                .with_context(|| format!("{what}: '{x}' is not an integer"))
        })
        .collect()
}

/// An inclusive box of voxels, or the whole gradient domain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndexBox {
    All,
    Voxels(IVec3, IVec3),
}

/// "x0,y0,z0,x1,y1,z1" (inclusive) or "all".
pub fn index_box(text: &str, what: &str) -> Result<IndexBox> {
    if text == "all" {
        return Ok(IndexBox::All);
    }
    match integers(text, what)?.as_slice() {
        [x0, y0, z0, x1, y1, z1] => Ok(IndexBox::Voxels(
            IVec3::new(*x0, *y0, *z0),
            IVec3::new(*x1, *y1, *z1),
        )),
        _ => bail!("an index box is six integers x0,y0,z0,x1,y1,z1 (got '{text}')"),
    }
}

/// The direction of a finite difference (`--fd`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FdDirection {
    /// Each voxel on its own.
    Voxels(Vec<IVec3>),
    /// All voxels of a box together.
    Box(IndexBox),
    /// Every voxel of the domain: ⟨g, 1⟩.
    Ones,
    /// Random ±1 per voxel of the domain.
    Random,
}

/// "voxels:x,y,z;x,y,z", "box:x0,y0,z0,x1,y1,z1", "ones" or "random".
pub fn fd_direction(spec: &str) -> Result<FdDirection> {
    Ok(match spec.split_once(':') {
        Some(("voxels", list)) => FdDirection::Voxels(
            list.split(';')
                .map(|v| match integers(v, "--fd voxels")?.as_slice() {
                    [x, y, z] => Ok(IVec3::new(*x, *y, *z)),
                    _ => bail!("--fd voxels: each voxel is x,y,z (got '{v}')"),
                })
                .collect::<Result<_>>()?,
        ),
        Some(("box", b)) => FdDirection::Box(index_box(b, "--fd box")?),
        None if spec == "ones" => FdDirection::Ones,
        None if spec == "random" => FdDirection::Random,
        _ => bail!(
            "--fd takes voxels:x,y,z;x,y,z, box:x0,y0,z0,x1,y1,z1, ones or random (got '{spec}')"
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_in_every_unit() {
        assert_eq!(duration("120s"), Ok(Duration::from_secs(120)));
        assert_eq!(duration(" 90 "), Ok(Duration::from_secs(90)));
        assert_eq!(duration("2m"), Ok(Duration::from_secs(120)));
        assert_eq!(duration("2min"), Ok(Duration::from_secs(120)));
        assert_eq!(duration("1.5h"), Ok(Duration::from_secs(5400)));
        assert_eq!(duration("250ms"), Ok(Duration::from_millis(250)));
        assert_eq!(duration("0s"), Ok(Duration::ZERO));
        for bad in ["", "s", "-1s", "2 parsecs", "1e400s", "nan", "10d"] {
            assert!(duration(bad).is_err(), "'{bad}' parsed");
        }
        assert!(duration("10d").unwrap_err().contains("unknown unit 'd'"));
        assert!(duration("5ns").unwrap_err().contains("ms, s, m, min or h"));
        assert!(duration("1e-10s")
            .unwrap_err()
            .contains("shorter than a nanosecond"));
        assert_eq!(duration("2e-3s"), Ok(Duration::from_millis(2)));
        assert_eq!(duration("1e2"), Ok(Duration::from_secs(100)));
    }

    #[test]
    fn index_boxes() {
        assert_eq!(index_box("all", "--image-of").unwrap(), IndexBox::All);
        assert_eq!(
            index_box("1,2,3,4,5,-6", "--image-of").unwrap(),
            IndexBox::Voxels(IVec3::new(1, 2, 3), IVec3::new(4, 5, -6))
        );
        let five = index_box("1,2,3,4,5", "--image-of").unwrap_err();
        assert!(five.to_string().contains("six integers"), "{five}");
        let word = index_box("1,2,x,4,5,6", "--image-of").unwrap_err();
        assert!(word.to_string().contains("--image-of: 'x'"), "{word}");
    }

    #[test]
    fn fd_directions() {
        assert_eq!(
            fd_direction("voxels:1,2,3;-4,5,6").unwrap(),
            FdDirection::Voxels(vec![IVec3::new(1, 2, 3), IVec3::new(-4, 5, 6)])
        );
        assert_eq!(
            fd_direction("box:0,0,0,1,1,1").unwrap(),
            FdDirection::Box(IndexBox::Voxels(IVec3::ZERO, IVec3::ONE))
        );
        assert_eq!(
            fd_direction("box:all").unwrap(),
            FdDirection::Box(IndexBox::All)
        );
        assert_eq!(fd_direction("ones").unwrap(), FdDirection::Ones);
        assert_eq!(fd_direction("random").unwrap(), FdDirection::Random);
        for bad in [
            "voxels:1,2",
            "voxels:1,2,3;4",
            "box:1,2,3",
            "zeros",
            "ones:1",
        ] {
            assert!(fd_direction(bad).is_err(), "'{bad}' parsed");
        }
    }
}
