//! The camera path: a smooth closed curve through the three rooms and their doorways, walked at
//! constant speed for several laps, with a small smooth perturbation that differs from lap to lap.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Floor-plan waypoints (metres) of one lap: room A -> door A|B -> room B -> door B|C -> room C
/// -> door C|A -> back to the start. Neighbours of a door waypoint sit on either side of it so the
/// spline crosses each doorway nearly at right angles.
const WAYPOINTS: [[f64; 2]; 11] = [
    [2.0, 1.4],
    [3.6, 1.8],
    [5.0, 2.0],
    [6.4, 2.0],
    [7.6, 2.6],
    [7.5, 4.0],
    [7.3, 5.6],
    [5.0, 6.2],
    [2.7, 5.6],
    [2.5, 4.0],
    [1.6, 2.8],
];

/// Spline samples per waypoint span used for the arc-length table.
const SAMPLES_PER_SPAN: usize = 256;

/// Camera height above the floor (metres), like a hand-held camera.
const EYE_HEIGHT: f64 = 1.45;

/// A closed Catmull-Rom curve, tabulated by arc length.
pub struct CameraPath {
    /// Cumulative arc length at each sample; `lengths[0] == 0`.
    lengths: Vec<f64>,
    /// Spline parameter (span index + fraction) at each sample.
    params: Vec<f64>,
    /// Phases of the perturbation terms, from the seed.
    phases: [f64; 6],
    /// Sideways offset (metres) and extra heading (radians) of every lap after the first,
    /// alternating in sign from lap to lap (a revisit on the other side of the corridor).
    lap_offset: f64,
    lap_yaw: f64,
}

/// Smooth 0 -> 1 over [0, 1] (and 0 before, 1 after).
fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

fn catmull_rom(t: f64) -> [f64; 2] {
    let n = WAYPOINTS.len();
    let span = (t.floor() as isize).rem_euclid(n as isize) as usize;
    let f = t - t.floor();
    let p = |k: isize| WAYPOINTS[((span as isize + k).rem_euclid(n as isize)) as usize];
    let (p0, p1, p2, p3) = (p(-1), p(0), p(1), p(2));
    let mut out = [0.0; 2];
    for axis in 0..2 {
        let (a, b, c, d) = (p0[axis], p1[axis], p2[axis], p3[axis]);
        out[axis] = 0.5
            * (2.0 * b
                + (-a + c) * f
                + (2.0 * a - 5.0 * b + 4.0 * c - d) * f * f
                + (-a + 3.0 * b - 3.0 * c + d) * f * f * f);
    }
    out
}

impl CameraPath {
    pub fn new(seed: u64) -> Self {
        let n = WAYPOINTS.len() * SAMPLES_PER_SPAN;
        let mut lengths = Vec::with_capacity(n + 1);
        let mut params = Vec::with_capacity(n + 1);
        let mut previous = catmull_rom(0.0);
        let mut total = 0.0;
        for i in 0..=n {
            let t = i as f64 / SAMPLES_PER_SPAN as f64;
            let point = catmull_rom(t);
            total += ((point[0] - previous[0]).powi(2) + (point[1] - previous[1]).powi(2)).sqrt();
            lengths.push(total);
            params.push(t);
            previous = point;
        }
        let mut rng = super::world::SplitMix64::new(seed ^ 0x7061_7468);
        let phases = std::array::from_fn(|_| rng.next_f64() * std::f64::consts::TAU);
        CameraPath { lengths, params, phases, lap_offset: 0.0, lap_yaw: 0.0 }
    }

    /// Offsets every lap after the first by `offset` metres sideways and `yaw` radians, alternating in
    /// sign; the change eases in over the first tenth of each lap.
    pub fn with_lap_offsets(mut self, offset: f64, yaw: f64) -> Self {
        self.lap_offset = offset;
        self.lap_yaw = yaw;
        self
    }

    /// This lap's share of the lap offsets at `progress`: 0 on the first lap, then ±1 (eased).
    fn lap_sign(&self, progress: f64) -> f64 {
        let lap = progress.floor();
        let sign = |lap: f64| {
            if lap < 1.0 {
                0.0
            } else if (lap as i64) % 2 == 1 {
                1.0
            } else {
                -1.0
            }
        };
        let (previous, current) = (sign(lap - 1.0), sign(lap));
        previous + (current - previous) * smoothstep((progress - lap) / 0.1)
    }

    /// Length of one lap in metres.
    pub fn lap_length(&self) -> f64 {
        *self.lengths.last().expect("table is never empty")
    }

    /// Floor-plan point at arc length `s` (wraps around the lap).
    fn point_at(&self, s: f64) -> [f64; 2] {
        let s = s.rem_euclid(self.lap_length());
        let k = self.lengths.partition_point(|&l| l < s).clamp(1, self.lengths.len() - 1);
        let (l0, l1) = (self.lengths[k - 1], self.lengths[k]);
        let f = if l1 > l0 { (s - l0) / (l1 - l0) } else { 0.0 };
        catmull_rom(self.params[k - 1] + f * (self.params[k] - self.params[k - 1]))
    }

    /// Camera-to-world pose at `progress` laps (0.0 = start of the first lap, 1.5 = middle of
    /// the second). The perturbation is a sum of sines of `progress` with frequencies that are not
    /// whole numbers, so it is smooth across lap boundaries yet different on every lap.
    pub fn pose(&self, progress: f64) -> Isometry3<f64> {
        let length = self.lap_length();
        let s = progress.rem_euclid(1.0) * length;
        let here = self.point_at(s);
        let ahead = self.point_at(s + 0.05);
        let behind = self.point_at(s - 0.05);
        let (tx, ty) = (ahead[0] - behind[0], ahead[1] - behind[1]);
        let norm = (tx * tx + ty * ty).sqrt().max(1e-9);
        let (tx, ty) = (tx / norm, ty / norm);
        let ph = &self.phases;
        let u = progress;
        let lateral = 0.08 * (std::f64::consts::TAU * 1.37 * u + ph[0]).sin()
            + 0.04 * (std::f64::consts::TAU * 2.91 * u + ph[1]).sin();
        let height = EYE_HEIGHT + 0.04 * (std::f64::consts::TAU * 1.73 * u + ph[2]).sin();
        // Looking around: the same sway at the same place on every lap, plus a per-lap offset.
        let sway = 0.30 * (std::f64::consts::TAU * 4.0 * s / length).sin();
        let yaw_jitter = 0.07 * (std::f64::consts::TAU * 1.19 * u + ph[3]).sin();
        let pitch = -0.06 + 0.04 * (std::f64::consts::TAU * 2.23 * u + ph[4]).sin();
        let roll = 0.02 * (std::f64::consts::TAU * 3.07 * u + ph[5]).sin();
        let side = self.lap_sign(progress);
        let lateral = lateral + side * self.lap_offset;
        let position = Vector3::new(here[0] - ty * lateral, here[1] + tx * lateral, height);
        let yaw = ty.atan2(tx) + sway + yaw_jitter + side * self.lap_yaw;
        Isometry3::from_parts(Translation3::from(position), camera_rotation(yaw, pitch, roll))
    }
}

/// Camera-to-world rotation for a camera looking horizontally along `yaw` (world z up),
/// then pitched (positive = up) and rolled about its optical axis. Columns are the camera's
/// x (right), y (down) and z (forward) axes in world coordinates, the TUM convention.
pub fn camera_rotation(yaw: f64, pitch: f64, roll: f64) -> UnitQuaternion<f64> {
    let forward = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
    let down = Vector3::new(0.0, 0.0, -1.0);
    let right = down.cross(&forward);
    let level = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, forward]));
    // Pitch about the camera's x axis (a positive angle turns +z towards -y, i.e. up), then roll.
    let tilt =
        Rotation3::from_axis_angle(&Vector3::x_axis(), pitch) * Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
    UnitQuaternion::from_rotation_matrix(&(level * tilt))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_follows_tum_axes() {
        let q = camera_rotation(0.0, 0.0, 0.0);
        let forward = q * Vector3::z();
        let down = q * Vector3::y();
        assert!((forward - Vector3::x()).norm() < 1e-12);
        assert!((down + Vector3::z()).norm() < 1e-12);
        let up_tilted = camera_rotation(0.0, 0.2, 0.0) * Vector3::z();
        assert!(up_tilted.z > 0.19, "positive pitch must look up: {up_tilted}");
    }

    #[test]
    fn path_is_closed_and_smooth() {
        let path = CameraPath::new(1);
        assert!(path.lap_length() > 15.0 && path.lap_length() < 30.0, "{}", path.lap_length());
        let a = path.point_at(0.0);
        let b = path.point_at(path.lap_length());
        assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
        // Consecutive poses at 1/1000 lap apart stay within a few centimetres.
        for i in 0..3000 {
            let p = path.pose(i as f64 / 1000.0).translation.vector;
            let q = path.pose((i + 1) as f64 / 1000.0).translation.vector;
            assert!((p - q).norm() < 0.05, "jump at {i}");
        }
    }
}
