//! Odometry consistency of loop candidates: could the tracker have drifted that far?
//!
//! Some aliasing no feature check can catch: two rooms furnished alike are one rigid scene to any
//! two-view geometry. The tracker's own poses tell them apart. Between two visits to one place the
//! tracker's position error grows by at most a fraction of the path travelled (odometry drift is
//! proportional to distance), so a true loop joins keyframes whose tracked positions differ by at
//! most `radius + max_drift × path`, where `radius` is how far apart two cameras seeing one place
//! may stand. A look-alike place elsewhere sits farther from the tracked position than that, as
//! long as the drift bound holds. This is the check RTAB-Map makes after optimising
//! (`RGBD/OptimizeMaxError`), made before: the candidate never reaches the optimiser.
//!
//! The same holds for orientation, and it catches what positions cannot: a verified pair whose
//! relative pose is wrong (a look-alike seen at another angle, a degenerate two-view fit). The
//! relative rotation verification measured and the one the tracker's poses give differ by the
//! verification's own error plus the tracker's heading drift, which also grows with the path; a
//! loop whose two rotations differ by more than `tolerance + max_rotation_drift × path` is rejected
//! before its wrong pose can bend the map.
//!
//! Keyframes without a tracker pose (a plain camera, a replay without `--poses`) are not checked.

use std::collections::HashMap;

use nalgebra::{Isometry3, UnitQuaternion, Vector3};

/// The drift bounds. A candidate passes when its keyframes' tracked positions are within
/// `radius_m + max_drift × path travelled between them`, and its verified relative rotation is
/// within `rotation_tolerance_deg + max_rotation_drift_deg × path` of the tracked one. A bound whose
/// rate is 0 is not checked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftBound {
    /// Position error the tracker may gather per metre travelled (0.1 = 10% of the path; 0 = positions
    /// not checked).
    pub max_drift: f64,
    /// Distance in metres between two cameras that still see one place (drift aside).
    pub radius_m: f64,
    /// Orientation error, in degrees, the tracker may gather per metre travelled (0 = rotations not
    /// checked).
    pub max_rotation_drift_deg: f64,
    /// How far, in degrees, a verified relative rotation may be off, drift aside.
    pub rotation_tolerance_deg: f64,
}

impl DriftBound {
    /// Whether either bound is checked.
    pub fn checks_anything(&self) -> bool {
        self.max_drift > 0.0 || self.max_rotation_drift_deg > 0.0
    }
}

/// Where the tracker put each keyframe, and how far it had travelled by then.
#[derive(Clone, Debug, Default)]
pub struct OdometryTrack {
    keyframes: HashMap<u64, Tracked>,
    /// The newest frame's.
    last: Option<Tracked>,
}

/// What the check found for one candidate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftCheck {
    /// Distance between the two keyframes' tracked positions.
    pub distance_m: f64,
    /// Path the tracker travelled between them.
    pub path_m: f64,
    /// Angle in degrees between the verified relative rotation and the tracked one (`None` without a
    /// verified rotation).
    pub rotation_deg: Option<f64>,
    /// Whether the tracked positions fit the position bound (true when it is not checked).
    pub position_consistent: bool,
    /// Whether the rotations fit the rotation bound (true when it is not checked).
    pub rotation_consistent: bool,
}

impl DriftCheck {
    pub fn consistent(&self) -> bool {
        self.position_consistent && self.rotation_consistent
    }
}

/// A frame's place on the tracker's path: its tracked pose (camera-to-world) and the path length up
/// to it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tracked {
    pub position: Vector3<f64>,
    pub rotation: UnitQuaternion<f64>,
    pub path_m: f64,
}

impl OdometryTrack {
    /// Extends the path with the tracker's pose (camera-to-world) of the next frame, in arrival
    /// order, keyframe or not.
    pub fn advance(&mut self, pose: &Isometry3<f64>) -> Tracked {
        let position = pose.translation.vector;
        let path_m = match self.last {
            Some(last) => last.path_m + (position - last.position).norm(),
            None => 0.0,
        };
        let tracked = Tracked { position, rotation: pose.rotation, path_m };
        self.last = Some(tracked);
        tracked
    }

    /// Remembers where keyframe `id` was tracked (from [`OdometryTrack::advance`]).
    pub fn keep(&mut self, id: u64, tracked: Tracked) {
        self.keyframes.insert(id, tracked);
    }

    /// Where keyframe `id` was tracked, if it came with a pose.
    pub fn tracked(&self, id: u64) -> Option<Tracked> {
        self.keyframes.get(&id).copied()
    }

    /// Keyframes with a tracked position.
    pub fn len(&self) -> usize {
        self.keyframes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// Checks a loop from a query tracked at `query` to keyframe `matched`, whose verification
    /// measured the query camera's rotation in the match camera's frame as `verified` (if it
    /// measured one); `None` when `matched` has no tracked pose.
    pub fn check(
        &self,
        query: Tracked,
        matched: u64,
        verified: Option<&UnitQuaternion<f64>>,
        bound: &DriftBound,
    ) -> Option<DriftCheck> {
        let matched = self.keyframes.get(&matched)?;
        let distance_m = (query.position - matched.position).norm();
        let path_m = (query.path_m - matched.path_m).abs();
        let tracked_rotation = matched.rotation.inverse() * query.rotation;
        let rotation_deg = verified.map(|verified| verified.angle_to(&tracked_rotation).to_degrees());
        let position_consistent = bound.max_drift <= 0.0 || distance_m <= bound.radius_m + bound.max_drift * path_m;
        let rotation_consistent = bound.max_rotation_drift_deg <= 0.0
            || rotation_deg
                .is_none_or(|angle| angle <= bound.rotation_tolerance_deg + bound.max_rotation_drift_deg * path_m);
        Some(DriftCheck { distance_m, path_m, rotation_deg, position_consistent, rotation_consistent })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64, y: f64) -> Isometry3<f64> {
        Isometry3::translation(x, y, 0.0)
    }

    const BOUND: DriftBound =
        DriftBound { max_drift: 0.1, radius_m: 1.0, max_rotation_drift_deg: 0.0, rotation_tolerance_deg: 10.0 };

    /// A track through `points`; the frames named in `keyframes` (by index) become keyframes of
    /// that id. Returns the track and each frame's place.
    fn walk(points: &[(f64, f64)], keyframes: &[usize]) -> (OdometryTrack, Vec<Tracked>) {
        let mut track = OdometryTrack::default();
        let mut places = Vec::new();
        for (i, &(x, y)) in points.iter().enumerate() {
            let tracked = track.advance(&at(x, y));
            if keyframes.contains(&i) {
                track.keep(i as u64, tracked);
            }
            places.push(tracked);
        }
        (track, places)
    }

    #[test]
    fn path_length_counts_every_frame_not_only_keyframes() {
        // A 10 m square walked back to near the start; only the first frame is a keyframe.
        let (track, places) = walk(&[(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0), (0.5, 0.0)], &[0]);
        let check = track.check(places[4], 0, None, &BOUND).unwrap();
        assert!((check.path_m - (30.0 + 100.25_f64.sqrt())).abs() < 1e-9, "{check:?}");
        assert!((check.distance_m - 0.5).abs() < 1e-12);
        assert!(check.consistent());
    }

    #[test]
    fn a_look_alike_place_beyond_the_drift_bound_fails() {
        // 20 m travelled: the bound is 1 + 0.1 * 20 = 3 m.
        let (track, places) = walk(&[(0.0, 0.0), (0.0, 11.5), (0.0, 3.0)], &[0]);
        let edge = track.check(places[2], 0, None, &BOUND).unwrap();
        assert!((edge.path_m - 20.0).abs() < 1e-9);
        assert!(edge.consistent(), "{edge:?}");
        let (track, places) = walk(&[(0.0, 0.0), (0.0, 11.55), (0.0, 3.1)], &[0]);
        let beyond = track.check(places[2], 0, None, &BOUND).unwrap();
        assert!(!beyond.consistent(), "{beyond:?}");
        // The same place seen from a look-alike room 4 m away after a 10 m walk.
        let (track, places) = walk(&[(0.0, 0.0), (5.0, 3.0), (4.0, 0.0)], &[0]);
        assert!(!track.check(places[2], 0, None, &BOUND).unwrap().consistent());
    }

    #[test]
    fn keyframes_without_a_tracked_position_are_not_checked() {
        let (track, places) = walk(&[(0.0, 0.0), (50.0, 0.0)], &[1]);
        assert_eq!(track.check(places[1], 0, None, &BOUND), None);
        assert!(track.check(places[0], 1, None, &BOUND).is_some());
        assert_eq!(track.len(), 1);
    }

    #[test]
    fn a_verified_rotation_beyond_the_rotation_bound_fails() {
        // The tracker turns the camera 90 degrees about the vertical while walking a 10 m loop; the
        // bound is 10 + 1.5 * 10 = 25 degrees.
        let bound = DriftBound { max_rotation_drift_deg: 1.5, ..BOUND };
        let yaw = |degrees: f64| UnitQuaternion::from_euler_angles(0.0, 0.0, degrees.to_radians());
        let mut track = OdometryTrack::default();
        let start = track.advance(&Isometry3::from_parts(Vector3::zeros().into(), yaw(0.0)));
        track.keep(0, start);
        track.advance(&Isometry3::from_parts(Vector3::new(5.0, 0.0, 0.0).into(), yaw(45.0)));
        let query = track.advance(&Isometry3::from_parts(Vector3::new(0.0, 0.0, 0.0).into(), yaw(90.0)));
        let check = |verified: f64, bound: &DriftBound| track.check(query, 0, Some(&yaw(verified)), bound).unwrap();
        let right = check(90.0, &bound);
        assert!(right.consistent() && right.rotation_deg.unwrap() < 1e-9, "{right:?}");
        assert!(check(114.0, &bound).consistent());
        let wrong = check(116.0, &bound);
        assert!(!wrong.consistent() && wrong.position_consistent && !wrong.rotation_consistent, "{wrong:?}");
        assert!((wrong.rotation_deg.unwrap() - 26.0).abs() < 1e-9);
        // The query camera's rotation in the match camera's frame, not the other way round.
        assert!(!check(-90.0, &bound).consistent());
        // Not checked without a verified rotation, or with a rate of 0.
        assert!(track.check(query, 0, None, &bound).unwrap().consistent());
        assert!(check(-90.0, &BOUND).consistent());
        assert!(BOUND.checks_anything());
        assert!(DriftBound { max_drift: 0.0, ..bound }.checks_anything());
        assert!(!DriftBound { max_drift: 0.0, ..BOUND }.checks_anything());
    }
}
