//! Rotations in the estimates exchange: the quaternion columns of a rotation
//! (`quat_<q1>_<q2>_<q3>_w|x|y|z`), read as its Euler angles.

use polars::prelude::*;

use crate::linalg::Vector;
use crate::linalg::so3::{self, EulerRotation};

/// The quaternion columns of a rotation: `quat_<q1>_<q2>_<q3>_w`, `_x`, `_y`, `_z`.
pub fn quaternion_columns(quantities: &[String], r: &EulerRotation) -> Vec<String> {
    let stem = quantities[r.first..r.first + 3].join("_");
    ["w", "x", "y", "z"]
        .iter()
        .map(|c| format!("quat_{stem}_{c}"))
        .collect()
}

/// The Euler angles (in the rotation's unit) of a quaternion per row: null where a component
/// is null or the quaternion is zero or not finite (the run then reports it).
pub(super) fn euler_columns(r: &EulerRotation, quat: &[Float64Chunked]) -> [Float64Chunked; 3] {
    let scale = if r.degrees {
        180.0 / std::f64::consts::PI
    } else {
        1.0
    };
    let rows: Vec<Option<Vector<3>>> = (0..quat[0].len())
        .map(|i| {
            let q = [
                quat[0].get(i)?,
                quat[1].get(i)?,
                quat[2].get(i)?,
                quat[3].get(i)?,
            ];
            so3::matrix_of_quaternion(&q).map(|m| so3::euler_of_matrix(&m) * scale)
        })
        .collect();
    [0, 1, 2].map(|j| rows.iter().map(|e| e.map(|e| e[j])).collect())
}
