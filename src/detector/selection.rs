//! Keyframe selection: which frames of a (30 Hz) stream become keyframes.
//!
//! A frame becomes a keyframe when every enabled rule accepts it:
//! - `every_nth`: at least N frames after the previous keyframe (counted over every frame offered,
//!   so with N = 3 frames 0, 3, 6, ... are taken when nothing else rejects);
//! - `min_period_secs`: at least this many seconds from the previous keyframe's stamp, on either side: a
//!   frame delivered late, stamped a moment before the last keyframe, is as close to it as one a moment
//!   after. A jump back by more than the period (a replay that restarts) passes: time went backwards,
//!   so the previous keyframe says nothing about this one;
//! - `novelty_min_distance`: the descriptor is at least this far (Euclidean) from the previous keyframe's.
//!
//! The first frame is always a keyframe. The default (`config/ecm_lcd.yaml`) is the time rule alone at
//! 0.5 s: it does not depend on the frame rate (30 Hz becomes about 2 keyframes/s, a 1 Hz sequence keeps
//! every frame), adjacent keyframes still overlap for hand-held motion, and it is decided before the
//! network runs. Novelty is off by default because its distance scale depends on the descriptor mode.
//!
//! The cheap rules run first ([`KeyframeSelector::offer`]) so a caller only computes the descriptor
//! (runs the network) for frames that the novelty rule still has to judge.

use crate::descriptor::distance;
use crate::types::Stamp;

/// The selection rules; every enabled rule must accept a frame.
#[derive(Clone, Debug, PartialEq)]
pub struct SelectionParams {
    /// Take at most every N-th frame (counted since the last keyframe); 1 disables the rule.
    pub every_nth: usize,
    /// Keyframes are at least this many seconds apart; 0 disables the rule.
    pub min_period_secs: f64,
    /// A keyframe's descriptor is at least this far from the last keyframe's; 0 disables the rule.
    pub novelty_min_distance: f32,
}

/// What the cheap rules say about a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Not a keyframe; no descriptor needed.
    Reject,
    /// A keyframe (already recorded as the last one).
    Accept,
    /// The cheap rules pass; call [`KeyframeSelector::offer_descriptor`] with the frame's descriptor.
    NeedsDescriptor,
}

/// Applies [`SelectionParams`] to a stream of frames, remembering the last keyframe.
#[derive(Clone, Debug)]
pub struct KeyframeSelector {
    params: SelectionParams,
    /// Frames offered since the last keyframe, this one included once counted.
    frames_since_keyframe: usize,
    last_stamp: Option<Stamp>,
    /// Kept only while the novelty rule is on.
    last_descriptor: Option<Vec<f32>>,
}

impl KeyframeSelector {
    pub fn new(params: SelectionParams) -> Self {
        KeyframeSelector { params, frames_since_keyframe: 0, last_stamp: None, last_descriptor: None }
    }

    pub fn params(&self) -> &SelectionParams {
        &self.params
    }

    /// Changes the rules at run time; the last keyframe is kept.
    pub fn set_params(&mut self, params: SelectionParams) {
        self.params = params;
    }

    /// Whether the novelty rule is on (frames passing the cheap rules need a descriptor).
    pub fn needs_descriptor(&self) -> bool {
        self.params.novelty_min_distance > 0.0
    }

    /// First step for every frame, in stream order: counts it and applies the cheap rules.
    pub fn offer(&mut self, stamp: Stamp) -> Verdict {
        self.frames_since_keyframe = self.frames_since_keyframe.saturating_add(1);
        let Some(last_stamp) = self.last_stamp else {
            return self.accept_unless_novelty_pending(stamp);
        };
        if self.frames_since_keyframe < self.params.every_nth {
            return Verdict::Reject;
        }
        let min_period_nanos = (self.params.min_period_secs * 1e9).round() as i64;
        let elapsed = stamp.nanos.saturating_sub(last_stamp.nanos);
        if elapsed.saturating_abs() < min_period_nanos {
            return Verdict::Reject;
        }
        self.accept_unless_novelty_pending(stamp)
    }

    fn accept_unless_novelty_pending(&mut self, stamp: Stamp) -> Verdict {
        if self.needs_descriptor() {
            Verdict::NeedsDescriptor
        } else {
            self.record(stamp, None);
            Verdict::Accept
        }
    }

    fn record(&mut self, stamp: Stamp, descriptor: Option<&[f32]>) {
        self.frames_since_keyframe = 0;
        self.last_stamp = Some(stamp);
        self.last_descriptor = descriptor.map(<[f32]>::to_vec);
    }

    /// Continues after a keyframe an earlier run selected (a restart from a keyframe store): the
    /// rules then judge the next frame as they would have without the restart.
    pub fn resume_after(&mut self, stamp: Stamp, descriptor: &[f32]) {
        self.record(stamp, Some(descriptor));
    }

    /// Second step, after [`Verdict::NeedsDescriptor`]: the novelty rule; `true` = a keyframe (recorded).
    /// Errors when the descriptor's length differs from the previous keyframe's.
    pub fn offer_descriptor(&mut self, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<bool> {
        let novel = match &self.last_descriptor {
            Some(last) => {
                anyhow::ensure!(
                    last.len() == descriptor.len(),
                    "descriptor has {} values, the previous keyframe's had {}",
                    descriptor.len(),
                    last.len()
                );
                // NaN compares false: a broken descriptor never counts as novel.
                distance(descriptor, last) >= self.params.novelty_min_distance
            }
            None => true,
        };
        if novel {
            self.record(stamp, Some(descriptor));
        }
        Ok(novel)
    }

    /// Both steps at once, for callers that have the descriptor anyway. Errors when the novelty rule
    /// needs a descriptor and none is given.
    pub fn accept(&mut self, stamp: Stamp, descriptor: Option<&[f32]>) -> anyhow::Result<bool> {
        match self.offer(stamp) {
            Verdict::Reject => Ok(false),
            Verdict::Accept => Ok(true),
            Verdict::NeedsDescriptor => {
                let descriptor = descriptor.ok_or_else(|| {
                    anyhow::anyhow!("frame at {stamp}: the novelty rule is on but no descriptor was given")
                })?;
                self.offer_descriptor(stamp, descriptor)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn off() -> SelectionParams {
        SelectionParams { every_nth: 1, min_period_secs: 0.0, novelty_min_distance: 0.0 }
    }

    /// Frame i at i/30 s.
    fn frame_stamp(i: usize) -> Stamp {
        Stamp::from_nanos(i as i64 * 1_000_000_000 / 30)
    }

    fn accepted(selector: &mut KeyframeSelector, frames: usize) -> Vec<usize> {
        (0..frames).filter(|&i| selector.accept(frame_stamp(i), None).unwrap()).collect()
    }

    #[test]
    fn all_rules_off_keeps_every_frame() {
        assert_eq!(accepted(&mut KeyframeSelector::new(off()), 5), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn every_nth_frame() {
        let mut s = KeyframeSelector::new(SelectionParams { every_nth: 3, ..off() });
        assert_eq!(accepted(&mut s, 10), vec![0, 3, 6, 9]);
    }

    #[test]
    fn minimum_period() {
        // 0.1 s at 30 Hz: frame 3 is exactly 0.1 s after frame 0.
        let mut s = KeyframeSelector::new(SelectionParams { min_period_secs: 0.1, ..off() });
        assert_eq!(accepted(&mut s, 10), vec![0, 3, 6, 9]);
        let mut s = KeyframeSelector::new(SelectionParams { min_period_secs: 0.5, ..off() });
        assert_eq!(accepted(&mut s, 31), vec![0, 15, 30]);
        // A frame delivered late, stamped within the period before the last keyframe, is rejected;
        // time jumping back by more (a replay that restarts) passes the time rule.
        assert!(!s.accept(frame_stamp(29), None).unwrap());
        assert!(!s.accept(frame_stamp(16), None).unwrap());
        assert!(s.accept(frame_stamp(2), None).unwrap());
        // The period is then measured from the restarted frame.
        assert!(!s.accept(frame_stamp(3), None).unwrap());
        assert!(s.accept(frame_stamp(17), None).unwrap());
    }

    #[test]
    fn rules_combine() {
        // Every 2nd frame and 0.1 s: the period is the stricter rule here.
        let mut s = KeyframeSelector::new(SelectionParams { every_nth: 2, min_period_secs: 0.1, ..off() });
        assert_eq!(accepted(&mut s, 10), vec![0, 3, 6, 9]);
        // Every 4th frame and 0.1 s: the count is the stricter.
        let mut s = KeyframeSelector::new(SelectionParams { every_nth: 4, min_period_secs: 0.1, ..off() });
        assert_eq!(accepted(&mut s, 10), vec![0, 4, 8]);
    }

    #[test]
    fn novelty_runs_after_the_cheap_rules() {
        let mut s = KeyframeSelector::new(SelectionParams { every_nth: 2, novelty_min_distance: 1.0, ..off() });
        assert!(s.needs_descriptor());
        // First frame: needs the descriptor, always novel.
        assert_eq!(s.offer(frame_stamp(0)), Verdict::NeedsDescriptor);
        assert!(s.offer_descriptor(frame_stamp(0), &[0.0, 0.0]).unwrap());
        // Frame 1: rejected by the count, no descriptor needed.
        assert_eq!(s.offer(frame_stamp(1)), Verdict::Reject);
        // Frame 2: distance 0.5 < 1, not novel.
        assert_eq!(s.offer(frame_stamp(2)), Verdict::NeedsDescriptor);
        assert!(!s.offer_descriptor(frame_stamp(2), &[0.3, 0.4]).unwrap());
        // Frame 3: the count keeps running since the last keyframe, so it passes; distance 1 is novel.
        assert_eq!(s.offer(frame_stamp(3)), Verdict::NeedsDescriptor);
        assert!(s.offer_descriptor(frame_stamp(3), &[0.6, 0.8]).unwrap());
        // Frame 4 fails the count (no descriptor needed even though one is given); frame 5 is measured
        // against the new keyframe (distance 0, not novel); frame 6 is novel again.
        assert!(!s.accept(frame_stamp(4), Some(&[0.0, 0.0])).unwrap());
        assert!(!s.accept(frame_stamp(5), Some(&[0.6, 0.8])).unwrap());
        assert!(s.accept(frame_stamp(6), Some(&[0.0, 0.0])).unwrap());
        // Missing or mismatched descriptors are errors, not silent decisions.
        assert!(!s.accept(frame_stamp(7), None).unwrap());
        assert!(s.accept(frame_stamp(8), None).unwrap_err().to_string().contains("novelty"));
        assert!(s.offer_descriptor(frame_stamp(9), &[0.0; 3]).is_err());
        // NaN is never novel.
        assert!(!s.offer_descriptor(frame_stamp(10), &[f32::NAN, 0.0]).unwrap());
    }
}
