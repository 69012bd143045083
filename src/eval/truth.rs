//! Loop ground truth: which earlier frames (or database images) each query truly revisits,
//! either derived from camera poses or read from an explicit loops file.
//!
//! Pose rule (defaults in [`PoseLoopCriteria::default`]): frame `j` is a true match of query `i`
//! when `j` is at least `min_gap_s` seconds older than `i`, the camera positions are within
//! `max_distance_m` and the optical axes (camera +z) within `max_angle_deg`. Each frame takes the
//! pose of the nearest ground-truth stamp; a frame whose nearest pose is more than
//! `max_stamp_offset_s` away has no pose: as a query its truth is unknown (it is left out of the
//! metrics), and as a match it is neither right nor wrong (a query whose best match it is is left
//! out too: ground truth that starts after the images, as TUM's often does, would otherwise count
//! a right match to an early frame as a false loop).

use crate::types::Stamp;
use anyhow::{bail, Context, Result};
use nalgebra::{Isometry3, Vector3};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet};
use std::ops::Range;
use std::path::{Path, PathBuf};

static NO_MATCHES: BTreeSet<usize> = BTreeSet::new();

/// For each query (by replay index), the set of its true matches; queries not listed have none
/// unless they are marked unknown.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoopTruth {
    matches: BTreeMap<usize, BTreeSet<usize>>,
    unknown: BTreeSet<usize>,
    /// Frames (references) with no pose: whether a match to one is right is unknown.
    unknown_matches: BTreeSet<usize>,
}

impl LoopTruth {
    /// True matches of `query`: `None` when its truth is unknown (no pose), else the set
    /// (empty for a query that revisits nothing).
    pub fn matches(&self, query: usize) -> Option<&BTreeSet<usize>> {
        if self.unknown.contains(&query) {
            None
        } else {
            Some(self.matches.get(&query).unwrap_or(&NO_MATCHES))
        }
    }

    /// Queries that have at least one true match, in order.
    pub fn positive_queries(&self) -> impl Iterator<Item = usize> + '_ {
        self.matches.iter().filter(|(_, m)| !m.is_empty()).map(|(q, _)| *q)
    }

    pub fn unknown_queries(&self) -> &BTreeSet<usize> {
        &self.unknown
    }

    /// Records that `query` truly matches `matched` (adds to its set).
    pub fn insert(&mut self, query: usize, matched: usize) {
        self.matches.entry(query).or_default().insert(matched);
    }

    /// Refuses indexes outside the data: a query at or past `queries`, a match at or past
    /// `references` (a loops file for another set, or off by one), and truth that knows no query
    /// at all (ground truth whose stamps overlap no frame).
    pub fn check_within(&self, queries: usize, references: usize) -> Result<()> {
        if let Some((&q, _)) = self.matches.iter().find(|(&q, _)| q >= queries) {
            bail!("the loop truth names query {q}, but there are only {queries} queries (0..{queries})");
        }
        for (q, matched) in &self.matches {
            if let Some(m) = matched.iter().find(|&&m| m >= references) {
                bail!("the loop truth matches query {q} to {m}, but there are only {references} references (0..{references})");
            }
        }
        if queries > 0 && (0..queries).all(|q| self.unknown.contains(&q)) {
            bail!("the ground truth covers none of the {queries} frames (no pose near any frame's stamp)");
        }
        Ok(())
    }

    /// Marks `query` as having unknown truth; it is then left out of the metrics.
    pub fn mark_unknown(&mut self, query: usize) {
        self.unknown.insert(query);
    }

    /// Marks frame `matched` as one whose matches are neither right nor wrong (it has no pose).
    pub fn mark_unknown_match(&mut self, matched: usize) {
        self.unknown_matches.insert(matched);
    }

    /// Whether a match to `matched` is neither right nor wrong.
    pub fn is_unknown_match(&self, matched: usize) -> bool {
        self.unknown_matches.contains(&matched)
    }

    /// Takes `frames` out of every query's true matches: references that could not be read, which
    /// no query can match. A query left with none is unknown (left out of the metrics, as one
    /// without a pose): it revisits a place the detector was not given, so no answer of its is
    /// right, nor is a match to the unreadable frame's neighbour plainly wrong.
    pub fn without_references(&mut self, frames: &[usize]) {
        for (query, matched) in self.matches.iter_mut() {
            let had = !matched.is_empty();
            frames.iter().for_each(|frame| {
                matched.remove(frame);
            });
            if had && matched.is_empty() {
                self.unknown.insert(*query);
            }
        }
    }

    /// The truth of a database/query set cut from one sequence: the frames `queries`, in the order
    /// given, against the frames `references`, each renumbered from 0. A query keeps only its
    /// matches among the references, and stays unknown where it was.
    pub fn between(&self, queries: impl IntoIterator<Item = usize>, references: Range<usize>) -> LoopTruth {
        let mut cut = LoopTruth::default();
        for (q, frame) in queries.into_iter().enumerate() {
            match self.matches(frame) {
                None => cut.mark_unknown(q),
                Some(matched) => {
                    for m in matched.range(references.clone()) {
                        cut.insert(q, m - references.start);
                    }
                }
            }
        }
        for m in self.unknown_matches.range(references.clone()) {
            cut.mark_unknown_match(m - references.start);
        }
        cut
    }
}

/// Rules for "same place" between two posed frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseLoopCriteria {
    pub max_distance_m: f64,
    pub max_angle_deg: f64,
    pub min_gap_s: f64,
    pub max_stamp_offset_s: f64,
}

impl Default for PoseLoopCriteria {
    /// 1 m, 30°, 20 s, 0.05 s. Why, for TUM-scale indoor sequences: with things 1-4 m away, two
    /// views whose centres are within 1 m and whose axes are within 30° (about half the 62°
    /// horizontal field of view of the Kinect) share most of what they see; 20 s excludes the
    /// trivially similar recent frames (6-10 m of hand-held motion at 0.3-0.5 m/s) so that only
    /// real revisits count; 0.05 s is half the spacing of frames at 10 Hz and five samples of the
    /// 100 Hz TUM ground truth, enough for unsynchronised stamps and too little to misplace a frame.
    fn default() -> Self {
        PoseLoopCriteria { max_distance_m: 1.0, max_angle_deg: 30.0, min_gap_s: 20.0, max_stamp_offset_s: 0.05 }
    }
}

impl PoseLoopCriteria {
    /// Raises `params`' `detector.exclude_recent.seconds` to `min_gap_s` where it is lower, and
    /// returns the value it had if so. The truth counts no frame younger than the gap as a revisit,
    /// so a detector under evaluation must not look there either: a query's best match would
    /// otherwise often be the same place seen a few seconds earlier (a slow hand-held camera's
    /// view), scored as a wrong loop, and the figures would measure how long the camera lingers
    /// rather than the detector.
    pub fn exclude_younger_than_the_gap(&self, params: &mut crate::config::Params) -> Result<Option<f64>> {
        const NAME: &str = "detector.exclude_recent.seconds";
        let configured = params.detector().exclude_recent_secs;
        if configured >= self.min_gap_s {
            return Ok(None);
        }
        params
            .set(NAME, crate::config::ParamValue::Double(self.min_gap_s))
            .map_err(|e| anyhow::anyhow!("the loop truth's gap of {} s as {NAME}: {e}", self.min_gap_s))?;
        Ok(Some(configured))
    }
}

/// Ground-truth poses of each query stamp: the pose at the nearest ground-truth stamp, or `None`
/// if that is farther than `max_offset_s`. `groundtruth` need not be sorted.
pub fn poses_at_stamps(
    stamps: &[Stamp],
    groundtruth: &[(Stamp, Isometry3<f64>)],
    max_offset_s: f64,
) -> Vec<Option<Isometry3<f64>>> {
    let mut sorted: Vec<&(Stamp, Isometry3<f64>)> = groundtruth.iter().collect();
    sorted.sort_by_key(|(s, _)| *s);
    let sorted_stamps: Vec<Stamp> = sorted.iter().map(|(s, _)| *s).collect();
    let max_offset = Stamp::from_nanos((max_offset_s * 1e9).round() as i64);
    stamps
        .iter()
        .map(|&stamp| crate::types::nearest_stamp(&sorted_stamps, stamp, max_offset).map(|i| sorted[i].1))
        .collect()
}

/// Loop truth of a sequence from its frame stamps (replay order) and ground-truth poses.
pub fn loop_truth_from_poses(
    stamps: &[Stamp],
    groundtruth: &[(Stamp, Isometry3<f64>)],
    criteria: &PoseLoopCriteria,
) -> LoopTruth {
    let poses = poses_at_stamps(stamps, groundtruth, criteria.max_stamp_offset_s);
    let axes: Vec<Option<(Vector3<f64>, Vector3<f64>)>> =
        poses.iter().map(|p| p.map(|p| (p.translation.vector, p.rotation * Vector3::z()))).collect();
    let cos_max = criteria.max_angle_deg.to_radians().cos();
    let min_gap = (criteria.min_gap_s * 1e9).round() as i64;
    let per_query: Vec<Option<Vec<usize>>> = (0..stamps.len())
        .into_par_iter()
        .map(|q| {
            let (position, axis) = axes[q]?;
            // Only frames replayed before the query are in its history (with a gap of 0, not itself).
            let found = (0..q)
                .filter(|&m| stamps[q].nanos - stamps[m].nanos >= min_gap)
                .filter(|&m| match axes[m] {
                    Some((p, a)) => (p - position).norm() <= criteria.max_distance_m && a.dot(&axis) >= cos_max,
                    None => false,
                })
                .collect();
            Some(found)
        })
        .collect();
    let mut truth = LoopTruth::default();
    for (q, found) in per_query.into_iter().enumerate() {
        match found {
            None => {
                truth.mark_unknown(q);
                truth.mark_unknown_match(q);
            }
            Some(found) => found.into_iter().for_each(|m| truth.insert(q, m)),
        }
    }
    truth
}

/// Parses an explicit loops file: lines `query_index,match_index match_index ...` (indexes in
/// replay order, or database indexes in database/query mode). A query with no loop may be listed
/// with nothing after the comma or left out. Blank lines and `#` comments are skipped; an
/// optional header line whose first field starts with a letter (e.g. `query,matches`) is allowed first.
pub fn parse_loops(text: &str) -> Result<LoopTruth> {
    let mut truth = LoopTruth::default();
    let mut seen = BTreeSet::new();
    let mut first_content = true;
    for (number, line) in text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())) {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let is_first = std::mem::replace(&mut first_content, false);
        let (query_text, matches_text) = line.split_once(',').with_context(|| {
            format!("line {number}: expected `query_index,match_index ...`, found {}", crate::io::excerpt(line, 80))
        })?;
        let query_text = query_text.trim();
        if is_first && query_text.starts_with(|c: char| c.is_ascii_alphabetic()) {
            continue; // header
        }
        let query: usize =
            query_text.parse().with_context(|| format!("line {number}: query index {query_text:?} is not a number"))?;
        if !seen.insert(query) {
            bail!("line {number}: query {query} is listed twice");
        }
        for field in matches_text.split_whitespace() {
            let matched: usize =
                field.parse().with_context(|| format!("line {number}: match index {field:?} is not a number"))?;
            truth.insert(query, matched);
        }
    }
    Ok(truth)
}

pub fn read_loops(path: &Path) -> Result<LoopTruth> {
    let text = crate::io::read_capped_text(path, crate::io::limits::TEXT_LIST, "loops file")?;
    parse_loops(&text).with_context(|| format!("in loops file {}", path.display()))
}

/// Image files directly in `dir`, in name order (numbers by value:
/// [`crate::io::tum::image_files_in_name_order`]): how the database and query folders of
/// database/query mode are indexed.
pub fn images_in_name_order(dir: &Path) -> Result<Vec<PathBuf>> {
    let images = crate::io::tum::image_files_in_name_order(dir)
        .with_context(|| format!("listing image folder {}", dir.display()))?;
    if images.is_empty() {
        bail!("image folder {} holds no png, jpg or bmp files", dir.display());
    }
    Ok(images)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::camera_rotation;
    use nalgebra::Translation3;

    #[test]
    fn truth_outside_the_data_is_refused() {
        let truth = parse_loops("3,1\n4,0 2\n").unwrap();
        assert!(truth.check_within(5, 5).is_ok());
        let err = truth.check_within(4, 5).unwrap_err().to_string();
        assert!(err.contains("query 4") && err.contains("only 4 queries"), "{err}");
        let err = truth.check_within(5, 2).unwrap_err().to_string();
        assert!(err.contains("to 2") && err.contains("only 2 references"), "{err}");
        let mut none = LoopTruth::default();
        (0..3).for_each(|q| none.mark_unknown(q));
        assert!(none.check_within(3, 3).unwrap_err().to_string().contains("covers none of the 3 frames"));
    }

    #[test]
    fn a_cut_keeps_the_matches_among_its_references_renumbered() {
        let mut truth = parse_loops("5,0 3\n6,1 2 4\n7,6\n").unwrap();
        truth.mark_unknown(8);
        let cut = truth.between(5..9, 1..4);
        assert_eq!(cut.matches(0).unwrap().iter().copied().collect::<Vec<_>>(), vec![2]);
        assert_eq!(cut.matches(1).unwrap().iter().copied().collect::<Vec<_>>(), vec![0, 1]);
        assert!(cut.matches(2).unwrap().is_empty(), "its only match is outside the references");
        assert_eq!(cut.matches(3), None, "unknown stays unknown");
        assert_eq!(cut.positive_queries().collect::<Vec<_>>(), vec![0, 1]);
        assert!(cut.check_within(4, 3).is_ok());
        let backwards = truth.between((5..9).rev(), 1..4);
        assert_eq!(backwards.matches(0), None, "frame 8 first");
        assert_eq!(backwards.matches(3).unwrap().iter().copied().collect::<Vec<_>>(), vec![2]);
    }

    fn pose(x: f64, y: f64, yaw_deg: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, y, 1.5), camera_rotation(yaw_deg.to_radians(), 0.0, 0.0))
    }

    fn secs(s: f64) -> Stamp {
        Stamp::from_secs_f64(1000.0 + s)
    }

    #[test]
    fn the_detector_under_evaluation_excludes_what_the_gap_excludes() {
        let criteria = PoseLoopCriteria::default();
        let mut params = crate::config::Params::default();
        assert_eq!(params.detector().exclude_recent_secs, criteria.min_gap_s, "the defaults agree");
        assert_eq!(criteria.exclude_younger_than_the_gap(&mut params).unwrap(), None);
        // A detector that looks at younger frames than the truth counts is kept from them.
        params.set_from_str("detector.exclude_recent.seconds", "10").unwrap();
        assert_eq!(criteria.exclude_younger_than_the_gap(&mut params).unwrap(), Some(10.0));
        assert_eq!(params.detector().exclude_recent_secs, criteria.min_gap_s);
        // A longer exclusion is the user's and stays.
        params.set_from_str("detector.exclude_recent.seconds", "45").unwrap();
        assert_eq!(criteria.exclude_younger_than_the_gap(&mut params).unwrap(), None);
        assert_eq!(params.detector().exclude_recent_secs, 45.0);
        // A gap beyond the parameter's range is refused, not clamped.
        let huge = PoseLoopCriteria { min_gap_s: 1e7, ..criteria };
        let err = huge.exclude_younger_than_the_gap(&mut params).unwrap_err();
        assert!(err.to_string().contains("detector.exclude_recent.seconds"), "{err:#}");
    }

    #[test]
    fn pose_truth_applies_distance_angle_and_gap() {
        // Frames at t = 0, 10, 30, 31, 32, 33, 34 s.
        let stamps: Vec<Stamp> = [0.0, 10.0, 30.0, 31.0, 32.0, 33.0, 34.0].iter().map(|&t| secs(t)).collect();
        let poses = [
            pose(0.0, 0.0, 0.0),
            pose(0.0, 0.0, 0.0),
            pose(0.9, 0.0, 0.0),  // 0.9 m from frame 0, 30 s later: loop with 0 and 1 (gap 20 s)
            pose(1.1, 0.0, 0.0),  // 1.1 m: too far
            pose(0.0, 0.0, 29.0), // 29 degrees: loop
            pose(0.0, 0.0, 31.0), // 31 degrees: not
            pose(0.0, 0.0, 0.0),  // same as 0 and 1, but frame 1 is only 24 s earlier: both
        ];
        let groundtruth: Vec<_> = stamps.iter().copied().zip(poses).collect();
        let truth = loop_truth_from_poses(&stamps, &groundtruth, &PoseLoopCriteria::default());
        let set = |v: &[usize]| v.iter().copied().collect::<BTreeSet<_>>();
        assert_eq!(truth.matches(0), Some(&set(&[])));
        assert_eq!(truth.matches(1), Some(&set(&[])));
        assert_eq!(truth.matches(2), Some(&set(&[0, 1])));
        assert_eq!(truth.matches(3), Some(&set(&[])));
        assert_eq!(truth.matches(4), Some(&set(&[0, 1])));
        assert_eq!(truth.matches(5), Some(&set(&[])));
        assert_eq!(truth.matches(6), Some(&set(&[0, 1])));
        // A gap of 25 s drops frame 1 (24 s before frame 6... and 20 s before frame 2).
        let strict = PoseLoopCriteria { min_gap_s: 25.0, ..PoseLoopCriteria::default() };
        let truth = loop_truth_from_poses(&stamps, &groundtruth, &strict);
        assert_eq!(truth.matches(2), Some(&set(&[0])));
        assert_eq!(truth.matches(6), Some(&set(&[0])));
        assert_eq!(truth.positive_queries().collect::<Vec<_>>(), vec![2, 4, 6]);
        // With no gap, a frame's matches are the frames replayed before it, never itself.
        let no_gap = PoseLoopCriteria { min_gap_s: 0.0, ..PoseLoopCriteria::default() };
        let truth = loop_truth_from_poses(&stamps, &groundtruth, &no_gap);
        assert_eq!(truth.matches(0), Some(&set(&[])));
        assert_eq!(truth.matches(1), Some(&set(&[0])));
        assert_eq!(truth.matches(6), Some(&set(&[0, 1, 2, 4])));
    }

    #[test]
    fn stamps_take_the_nearest_pose_within_the_offset() {
        let groundtruth =
            vec![(secs(1.0), pose(1.0, 0.0, 0.0)), (secs(0.0), pose(0.0, 0.0, 0.0)), (secs(2.0), pose(2.0, 0.0, 0.0))];
        let stamps = [secs(0.96), secs(1.03), secs(1.5), secs(-0.04), secs(2.06)];
        let poses = poses_at_stamps(&stamps, &groundtruth, 0.05);
        let xs: Vec<Option<f64>> = poses.iter().map(|p| p.map(|p| p.translation.x)).collect();
        assert_eq!(xs, vec![Some(1.0), Some(1.0), None, Some(0.0), None]);
        // Frames without a pose are unknown as queries and as matches.
        let stamps = [secs(0.0), secs(50.0)];
        let truth = loop_truth_from_poses(&stamps, &groundtruth, &PoseLoopCriteria::default());
        assert_eq!(truth.matches(1), None);
        assert_eq!(truth.unknown_queries().iter().copied().collect::<Vec<_>>(), vec![1]);
        assert!(truth.is_unknown_match(1) && !truth.is_unknown_match(0));
        // Cut into a database/query set, a reference keeps its unknown match, renumbered.
        let cut = truth.between([0], 1..2);
        assert!(cut.is_unknown_match(0));
    }

    #[test]
    fn loops_file_parses_and_names_bad_lines() {
        let truth = parse_loops("query,matches\n# comment\n5,1 2\n6,\n\n9, 3 \n").unwrap();
        assert_eq!(truth.matches(5).unwrap().iter().copied().collect::<Vec<_>>(), vec![1, 2]);
        assert!(truth.matches(6).unwrap().is_empty());
        assert!(truth.matches(7).unwrap().is_empty(), "an omitted query has no loop");
        assert_eq!(truth.positive_queries().collect::<Vec<_>>(), vec![5, 9]);
        for (text, expected) in [
            ("5,1\n6 2\n", "line 2: expected `query_index,match_index ...`"),
            ("5,1\nx,2\n", "line 2: query index \"x\" is not a number"),
            ("5,1 b\n", "line 1: match index \"b\" is not a number"),
            ("5,1\n\n5,2\n", "line 3: query 5 is listed twice"),
            ("-1,2\n", "line 1: query index \"-1\" is not a number"),
        ] {
            let err = parse_loops(text).unwrap_err();
            assert!(format!("{err:#}").contains(expected), "{text:?}: {err:#}");
        }
    }
}
