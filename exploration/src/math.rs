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
}
