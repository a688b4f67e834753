//! Poses as command lines spell them: comma-separated numbers, a bad one named by its column.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::track::Pose;

/// Text that is not the pose it should be.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PoseTextError {
    /// A field that is not a finite number.
    #[error("column {column}: {field:?} is not a finite number")]
    NotANumber {
        /// 1-based column.
        column: usize,
        /// The field as given.
        field: String,
    },
    /// Another count of numbers than the pose has.
    #[error("expected {layout} ({expected} numbers), found {found}")]
    Count {
        /// The fields, e.g. `x,y,z,yaw_deg`.
        layout: &'static str,
        /// Numbers the layout has.
        expected: usize,
        /// Numbers given.
        found: usize,
    },
    /// An attitude quaternion of zero length.
    #[error("the attitude quaternion is zero")]
    ZeroQuaternion,
}

/// Comma-separated finite numbers, exactly `N` of them, laid out as `layout` says.
fn numbers<const N: usize>(text: &str, layout: &'static str) -> Result<[f64; N], PoseTextError> {
    let values = text
        .split(',')
        .enumerate()
        .map(|(i, field)| match field.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(x),
            _ => Err(PoseTextError::NotANumber { column: i + 1, field: field.trim().to_string() }),
        })
        .collect::<Result<Vec<f64>, _>>()?;
    let found = values.len();
    values.try_into().map_err(|_| PoseTextError::Count { layout, expected: N, found })
}

/// `x,y,z,yaw_deg`: a position (m) and a heading in degrees from +x.
pub fn parse_pose_yaw(text: &str) -> Result<Pose, PoseTextError> {
    let [x, y, z, yaw_deg] = numbers(text, "x,y,z,yaw_deg")?;
    Ok(Pose { position: Vector3::new(x, y, z), yaw: yaw_deg.to_radians() })
}

/// `x,y,z,qw,qx,qy,qz`: a world position and a body attitude; the quaternion is normalised,
/// but must not be zero.
pub fn parse_pose_quaternion(text: &str) -> Result<(Vector3<f64>, UnitQuaternion<f64>), PoseTextError> {
    let [x, y, z, qw, qx, qy, qz] = numbers(text, "x,y,z,qw,qx,qy,qz")?;
    let q = Quaternion::new(qw, qx, qy, qz);
    if q.norm() <= 1e-9 {
        return Err(PoseTextError::ZeroQuaternion);
    }
    Ok((Vector3::new(x, y, z), UnitQuaternion::from_quaternion(q)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_parse_and_bad_ones_are_named() {
        let (p, q) = parse_pose_quaternion("1,2,3,2,0,0,0").unwrap();
        assert_eq!(p, Vector3::new(1.0, 2.0, 3.0));
        assert!((q.w - 1.0).abs() < 1e-12, "normalised");
        assert!(parse_pose_quaternion("1,2,3,1,0,0").unwrap_err().to_string().contains("7 numbers"));
        assert!(parse_pose_quaternion("1,2,x,1,0,0,0").unwrap_err().to_string().contains("column 3"));
        assert_eq!(parse_pose_quaternion("1,2,3,0,0,0,0"), Err(PoseTextError::ZeroQuaternion));
        let start = parse_pose_yaw("1, 2, 3, 90").unwrap();
        assert!((start.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12 && start.position.z == 3.0);
        assert!(parse_pose_yaw("1,2,inf,0").unwrap_err().to_string().contains("column 3"));
    }
}
