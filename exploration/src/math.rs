//! nalgebra aliases for the planar geometry used throughout.
//!
//! Names follow the `frame_from_frame` / `point_in_frame` convention: a
//! `Isometry2` called `world_from_robot` maps robot coordinates to world ones.

/// A point in a plane, metres.
pub type Point2 = nalgebra::Point2<f64>;
/// A displacement in a plane, metres.
pub type Vector2 = nalgebra::Vector2<f64>;
/// A rigid planar transform (rotation then translation).
pub type Isometry2 = nalgebra::Isometry2<f64>;

/// Wraps an angle into (-π, π].
pub fn normalize_angle(theta: f64) -> f64 {
    let wrapped = theta.rem_euclid(std::f64::consts::TAU);
    if wrapped > std::f64::consts::PI { wrapped - std::f64::consts::TAU } else { wrapped }
}

/// A number for a message: as Rust prints it, or in scientific notation
/// where that would take dozens of digits (a careless client's 1e300 or
/// 1e-300).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShortNumber(pub f64);

impl std::fmt::Display for ShortNumber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let size = self.0.abs();
        if size == 0.0 || !size.is_finite() || (1e-6..1e9).contains(&size) {
            write!(f, "{}", self.0)
        } else {
            write!(f, "{:e}", self.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn angles_wrap_into_half_open_interval() {
        assert!((normalize_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((normalize_angle(-PI) - PI).abs() < 1e-12);
        assert!((normalize_angle(0.5) - 0.5).abs() < 1e-12);
        assert!((normalize_angle(-0.5) + 0.5).abs() < 1e-12);
    }

    #[test]
    fn short_numbers_print_as_written_unless_they_take_dozens_of_digits() {
        let shown = |v: f64| ShortNumber(v).to_string();
        assert_eq!(shown(2.5), "2.5");
        assert_eq!(shown(-86400.0), "-86400");
        assert_eq!(shown(0.0), "0");
        assert_eq!(shown(f64::NAN), "NaN");
        assert_eq!(shown(f64::NEG_INFINITY), "-inf");
        assert_eq!(shown(1e300), "1e300");
        assert_eq!(shown(-1e-300), "-1e-300");
        assert_eq!(shown(f64::MAX).len(), "1.7976931348623157e308".len());
    }
}
