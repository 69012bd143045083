//! The whole per-frame path: image -> tensor -> feature map -> descriptor -> keyframe selection ->
//! detector -> loop candidates. The offline commands (replay, eval, demo) and the ROS node all
//! run frames through one [`Pipeline`], so they give the same answers.
//!
//! With a keyframe store attached ([`Pipeline::attach_store`]), every keyframe is committed to disk
//! before the detector sees it, so its candidates are never returned before the keyframe is durable.
//! A crash between the commit and the caller emitting the candidates loses those candidates, never
//! the keyframe.
//!
//! With verification on ([`Params::verification`]), each keyframe's local features are extracted and
//! kept, and a candidate is reported only when [`crate::verification`] finds one rigid geometry for
//! the pair. The nearest `verification.candidates` matches are all checked, as ORB-SLAM checks each
//! of its candidate keyframes, and those verified are reported most inliers first
//! ([`crate::verification::best_supported`]): a look-alike that outranks the true place no longer
//! hides it, nor is reported in its place where the true place is verified on more points. The best
//! match (for evaluation) is chosen the same way ([`Outcome::best_verified`]).

use std::collections::HashSet;
use std::path::Path;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use image::RgbImage;

use crate::config::{ParamError, ParamValue, Params};
use crate::descriptor::{Descriptor, DescriptorMode, Projection};
use crate::detector::selection::{KeyframeSelector, Verdict};
use crate::detector::store::{KeyframeRecord, KeyframeStore, StoreIdentity};
use crate::detector::{Detector, Match};
use crate::model::embedder::Embedder;
use crate::model::weights::resolve::{self, Resolved};
use crate::model::{Arch, Tap};
use crate::types::{DepthImage, FeatureMap, Frame, LoopCandidate, Recurring, RelativePose, Stamp, Verified};
use crate::verification::{
    best_supported_passing, Intrinsics, LocalFeatureKind, LocalFeatures, OdometryTrack, Tracked, Verification, Verifier,
};

/// Milliseconds spent per stage on one frame.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Timings {
    /// Resize, normalise and network forward (with verification, until the local features extracted
    /// beside it are ready too).
    pub network_ms: f64,
    pub descriptor_ms: f64,
    /// Database query and insertion.
    pub detector_ms: f64,
    /// Local features and geometric verification (0 when verification is off). The extraction may
    /// overlap the forward pass, so the stages can add up to more than the frame took.
    pub verification_ms: f64,
}

/// One image handed to the pipeline, with what came with it.
#[derive(Clone, Copy, Debug)]
pub struct Input<'a> {
    /// `Some`: a tracker's keyframe id (no selection, always inserted); `None`: a plain frame
    /// (selection decides, the id comes from the pipeline's counter).
    pub id: Option<u64>,
    pub stamp: Stamp,
    pub image: &'a RgbImage,
    /// Its depth image, where one came with it (metric poses).
    pub depth: Option<&'a DepthImage>,
    /// The camera frame it came in (stored with the keyframe; empty: unknown).
    pub frame_id: &'a str,
    /// The camera's pose in the tracker's map (world_T_camera), where the tracker gave one (stored
    /// with the keyframe).
    pub tracker_pose: Option<nalgebra::Isometry3<f64>>,
}

impl<'a> Input<'a> {
    /// A tracker's keyframe with nothing beside its image.
    pub fn keyframe(id: u64, stamp: Stamp, image: &'a RgbImage) -> Self {
        Input { id: Some(id), ..Input::frame(stamp, image) }
    }

    /// A plain frame with nothing beside its image.
    pub fn frame(stamp: Stamp, image: &'a RgbImage) -> Self {
        Input { id: None, stamp, image, depth: None, frame_id: "", tracker_pose: None }
    }
}

/// What became of one frame.
#[derive(Clone, Debug, Default)]
pub struct Outcome {
    /// The keyframe id, if the frame was taken as a keyframe.
    pub keyframe: Option<u64>,
    /// Loop candidates reported under the full policy.
    pub candidates: Vec<LoopCandidate>,
    /// The nearest eligible keyframe regardless of threshold and consistency (for evaluation).
    pub best: Option<Match>,
    /// Whether the best match passed geometric verification (`None`: verification off or no match).
    pub best_verified: Option<bool>,
    /// Candidates that passed the threshold but failed verification.
    pub rejected: usize,
    /// Of [`Outcome::rejected`], those whose features verified but whose tracker poses did not fit
    /// (`verification.max_drift`).
    pub rejected_by_odometry: usize,
    /// Of the candidates, those the odometry check (`verification.max_drift`) was set to make but
    /// could not: one of their keyframes has no tracker pose while others have.
    pub unchecked_by_odometry: usize,
    pub timings: Timings,
}

/// Network, descriptor, keyframe selection and detector, configured by [`Params`].
pub struct Pipeline {
    embedder: Embedder,
    params: Params,
    descriptor: Descriptor,
    /// The learned projection applied after the descriptor (`descriptor.projection`).
    projection: Option<Projection>,
    selector: KeyframeSelector,
    detector: Detector,
    next_id: u64,
    weights: Resolved,
    store: Option<KeyframeStore>,
    verifier: Option<Verifier>,
    /// Intrinsics from the camera driver (`sensor_msgs/CameraInfo`), when it sent them.
    camera_info: Option<Intrinsics>,
    /// Whether the best match is verified even when it is not a candidate (evaluation needs it; a
    /// node does not, and saves a check per keyframe).
    verify_best: bool,
    /// The tracker's path through the frames that came with poses (odometry consistency).
    odometry: OdometryTrack,
    /// The id of every keyframe in the detector's history, or dropped from it: an id is taken once.
    taken_ids: HashSet<u64>,
    /// Depth images that came with a frame of another size, and were left out.
    misfit_depths: Recurring,
    /// The newest frame stamp seen, and how many frames since came stamped no later.
    newest_stamp: Option<Stamp>,
    stamps_not_advancing: Recurring,
    /// Frames left out for showing nothing ([`MIN_CONTRAST`]).
    blank_frames: Recurring,
    /// Frames of a shape verification's intrinsics do not describe, and the last frame size they
    /// were scaled to ([`Pipeline::watch_frame_size`]).
    misfit_sizes: Recurring,
    scaled_to: Option<[u32; 2]>,
    /// Loops reported unchecked by odometry for want of a tracker pose on one keyframe.
    unchecked_loops: Recurring,
}

/// Counts of inputs that were well formed but could not be used as they came, each logged where it
/// occurs (the first and every hundredth); a node reports them in `/diagnostics`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct InputProblems {
    /// Frames stamped no later than a frame before them ([`Pipeline::watch_stamps`]).
    pub stamps_not_advancing: u64,
    /// Frames left out for showing nothing ([`MIN_CONTRAST`]).
    pub blank_frames: u64,
    /// Depth images of another size than their colour image, left out ([`Pipeline::fitting_depth`]).
    pub misfit_depths: u64,
    /// Frames of a shape that verification's intrinsics do not describe, verified without them
    /// ([`Pipeline::watch_frame_size`]).
    pub misfit_sizes: u64,
}

impl InputProblems {
    /// Each count with its name and what usually causes it.
    pub fn named(&self) -> [(&'static str, u64, &'static str); 4] {
        [
            (
                "stamps_not_advancing",
                self.stamps_not_advancing,
                "frames stamped no later than an earlier one (use_sim_time without /clock?)",
            ),
            ("blank_frames", self.blank_frames, "frames showing nothing, left out (a covered lens, darkness?)"),
            (
                "misfit_depths",
                self.misfit_depths,
                "depth images of another size than their colour image, left out (depth not registered?)",
            ),
            (
                "misfit_sizes",
                self.misfit_sizes,
                "frames of a shape the camera intrinsics do not describe, verified without them",
            ),
        ]
    }
}

/// The grey-level standard deviation under which an image shows nothing (a covered lens, darkness, a
/// view saturated white): its descriptor is the same wherever it was taken, so it would match every
/// other such image as the same place. Such frames are left out: no keyframe, no match.
pub const MIN_CONTRAST: f64 = 1.0;

/// The standard deviation of `image`'s grey levels (the mean of the three channels), over every
/// fourth pixel of every fourth row: enough to tell an image that shows nothing.
pub fn contrast(image: &RgbImage) -> f64 {
    let (mut n, mut sum, mut squares) = (0.0, 0.0, 0.0);
    for y in (0..image.height()).step_by(4) {
        for x in (0..image.width()).step_by(4) {
            let [r, g, b] = image.get_pixel(x, y).0;
            let grey = (r as f64 + g as f64 + b as f64) / 3.0;
            (n, sum, squares) = (n + 1.0, sum + grey, squares + grey * grey);
        }
    }
    if n == 0.0 {
        return 0.0;
    }
    let mean = sum / n;
    (squares / n - mean * mean).max(0.0).sqrt()
}

/// The descriptor as one name, the tap included: the mode's name for the modes on the head (`power`;
/// what stores made before taps existed hold), else e.g. `regional-3x3-mac@blocks.16`.
fn descriptor_name(descriptor: &Descriptor, tap: Tap) -> String {
    match tap {
        Tap::Head => descriptor.name(),
        tap => format!("{}@{tap}", descriptor.name()),
    }
}

impl Pipeline {
    /// Resolves the weights (`weights`, else the usual chain) and builds the pipeline.
    pub fn new(params: Params, weights: Option<&Path>) -> Result<Self> {
        Self::with_weights(params, resolve::resolve(weights)?)
    }

    pub fn with_weights(params: Params, weights: Resolved) -> Result<Self> {
        let arch: Arch = params.arch().parse()?;
        let network = weights.weights.for_arch(arch)?.network(false)?;
        log::info!("weights: {} -> {arch}, input {}²", weights.describe(), params.input_size());
        let mut embedder = Embedder::new(network, params.input_size()).context("network input size")?;
        embedder.set_tap(params.tap()?)?;
        let mut descriptor = params.descriptor()?;
        let raw_name = descriptor_name(&descriptor, embedder.tap());
        let projection = match params.projection() {
            Some(path) => {
                let projection = Projection::load(&path)?;
                ensure!(
                    projection.descriptor == raw_name && projection.in_dim() == descriptor.dim(),
                    "projection {} was learned on {} descriptors ({} values), but this pipeline computes {raw_name} ({} values)",
                    path.display(),
                    projection.descriptor,
                    projection.in_dim(),
                    descriptor.dim()
                );
                ensure!(
                    descriptor.mode != DescriptorMode::Paper,
                    "the paper descriptor is the reproduction: it takes no projection"
                );
                let network =
                    crate::descriptor::projection::network_name(params.arch(), &weights.sha256, params.input_size());
                if let Some(learned_on) = projection.network.as_ref().filter(|learned_on| **learned_on != network) {
                    anyhow::bail!(
                        "projection {} was learned on another network's descriptors ({learned_on}); this pipeline's \
                         is {network}: learn one for it (ecm-lcd learn-projection with the same --weights and params)",
                        path.display()
                    );
                }
                descriptor.projected_dim = Some(projection.out_dim());
                Some(projection)
            }
            None => None,
        };
        let verifier = params.verification(None).map(Verifier::new).transpose()?;
        if let Some(verifier) = &verifier {
            log::info!("geometric verification on: {:?}", verifier.params());
        } else if let Some(later) = params.verification_when_calibrated() {
            // Verification starts with the first camera intrinsics: XFeat's weights are found (or
            // fetched) now, so that neither the error nor the download comes in the middle of a run.
            if later.local_features == LocalFeatureKind::XFeat {
                crate::model::xfeat::resolve_weights(later.xfeat_weights.as_deref())?;
            }
        }
        let pipeline = Pipeline {
            embedder,
            selector: KeyframeSelector::new(params.selection()),
            detector: Detector::new(descriptor, params.detector()),
            descriptor,
            projection,
            params,
            next_id: 0,
            weights,
            store: None,
            verifier,
            camera_info: None,
            verify_best: true,
            odometry: OdometryTrack::default(),
            taken_ids: HashSet::new(),
            misfit_depths: Recurring::default(),
            newest_stamp: None,
            stamps_not_advancing: Recurring::default(),
            blank_frames: Recurring::default(),
            misfit_sizes: Recurring::default(),
            scaled_to: None,
            unchecked_loops: Recurring::default(),
        };
        log::info!("descriptor {} ({} values)", pipeline.descriptor_name(), pipeline.descriptor.dim());
        Ok(pipeline)
    }

    pub fn params(&self) -> &Params {
        &self.params
    }

    pub fn weights(&self) -> &Resolved {
        &self.weights
    }

    pub fn descriptor(&self) -> &Descriptor {
        &self.descriptor
    }

    pub fn detector(&self) -> &Detector {
        &self.detector
    }

    pub fn detector_mut(&mut self) -> &mut Detector {
        &mut self.detector
    }

    /// The descriptor as one name, the tap and any projection included, e.g.
    /// `regional-3x3-mac@blocks.16+pca256:1a2b3c4d5e6f` ([`Projection::identity`]).
    pub fn descriptor_name(&self) -> String {
        let name = descriptor_name(&self.descriptor, self.embedder.tap());
        match &self.projection {
            Some(projection) => name + &projection.identity(),
            None => name,
        }
    }

    /// The descriptor of a feature map: the descriptor mode's, then the projection where one is set.
    fn compute_descriptor(&self, feature_map: &FeatureMap) -> Result<Vec<f32>> {
        let descriptor = self.descriptor.compute(feature_map)?;
        Ok(match &self.projection {
            Some(projection) => projection.apply(&descriptor),
            None => descriptor,
        })
    }

    /// The network whose descriptors this pipeline computes ([`crate::descriptor::projection::network_name`]).
    pub fn network_name(&self) -> String {
        crate::descriptor::projection::network_name(self.params.arch(), &self.weights.sha256, self.params.input_size())
    }

    /// What this pipeline's descriptors depend on (a store must match it).
    pub fn store_identity(&self) -> StoreIdentity {
        StoreIdentity {
            weights_sha256: self.weights.sha256.clone(),
            arch: self.params.arch().to_string(),
            descriptor_mode: self.descriptor_name(),
            input_size: self.params.input_size(),
            dim: self.descriptor.dim(),
        }
    }

    /// Opens (or creates) the keyframe store at `path` and attaches it ([`Pipeline::attach_store`]).
    pub fn open_store(&mut self, path: &Path) -> Result<()> {
        let store = KeyframeStore::open_or_create(path, &self.store_identity())?;
        self.attach_store(store)
    }

    /// Makes `store` the keyframe history: its newest keyframes (all, or `detector.max_keyframes`)
    /// become the detector's database, counted ids continue after the largest stored id, and every
    /// later keyframe is appended to it. Refused when the store's identity differs from the pipeline's.
    pub fn attach_store(&mut self, mut store: KeyframeStore) -> Result<()> {
        let started = Instant::now();
        self.load_history(&store)?;
        self.resume_detector(&store)?;
        // Once the store is known to be this pipeline's (its identity checked by the load).
        self.compare_recorded_parameters(&store)?;
        store.record_parameters(&self.params.to_json().to_string())?;
        if let Some(max_id) = store.max_id() {
            self.next_id = self.next_id.max(max_id + 1);
        }
        // Selection goes on from the newest stored keyframe, so a restarted replay selects the
        // frames an uninterrupted one would (not the first frame after the restart regardless).
        if let Some((_, stamp, descriptor)) = store.last_keyframe()? {
            self.selector.resume_after(stamp, &descriptor);
        }
        log::info!(
            "keyframe database {}: {} keyframes stored, {} loaded (and indexed, if large) in {:.3} s, ids continue at {}",
            store.path().display(),
            store.len(),
            self.detector.db().len(),
            started.elapsed().as_secs_f64(),
            self.next_id
        );
        self.store = Some(store);
        // The tracker's path through the stored keyframes (their poses; frames between them were not
        // stored).
        for (id, (_, pose)) in self.stored_frames()? {
            if let Some(pose) = pose {
                let tracked = self.odometry.advance(&pose);
                self.odometry.keep(id, tracked);
            }
        }
        self.restore_local_features()
    }

    /// Says which parameters differ from those `store`'s keyframes were processed with: a continued
    /// run keeps the loops found before (the CSV is rewritten from them), found with those.
    fn compare_recorded_parameters(&self, store: &KeyframeStore) -> Result<()> {
        let (Some(recorded), false) = (store.recorded_parameters()?, store.is_empty()) else { return Ok(()) };
        let Ok(serde_json::Value::Object(before)) = serde_json::from_str::<serde_json::Value>(&recorded) else {
            return Ok(());
        };
        let now = self.params.to_json();
        let changed: Vec<String> = before
            .iter()
            .filter(|(name, value)| now.get(name.as_str()).is_some_and(|current| current != *value))
            .map(|(name, value)| format!("{name} {value} -> {}", now[name.as_str()]))
            .collect();
        if !changed.is_empty() {
            log::warn!(
                "keyframe database {}: its {} keyframes were processed with other parameters ({}); the loops found \
                 before keep those settings, the keyframes from now on get these",
                store.path().display(),
                store.len(),
                changed.join(", ")
            );
        }
        Ok(())
    }

    /// Makes the keyframes of `store` (opened read-only, say) the database that another session's
    /// frames are matched against (the database/query mode: a map made beforehand), with their kept
    /// local features, but none of what a continued run resumes (earlier queries, held-back loops,
    /// ids, selection, the tracker's path). Refused when the store's identity differs.
    pub fn load_map(&mut self, store: KeyframeStore) -> Result<()> {
        self.load_history(&store)?;
        log::info!("map {}: {} keyframes loaded", store.path().display(), self.detector.db().len());
        self.store = Some(store);
        self.restore_local_features()
    }

    /// The stored keyframes (all, or the newest `detector.max_keyframes`) as the detector's history,
    /// once the store is known to hold this pipeline's descriptors.
    fn load_history(&mut self, store: &KeyframeStore) -> Result<()> {
        store.identity().check_same(
            &format!("keyframe database {}", store.path().display()),
            &self.store_identity(),
            "this pipeline",
        )?;
        let limit = Some(self.params.detector().max_keyframes).filter(|&n| n > 0);
        self.detector.replace_history(store.load_db(limit)?)?;
        let db = self.detector.db();
        self.taken_ids = (0..db.len()).map(|position| db.id(position)).collect();
        Ok(())
    }

    /// Gives the detector what the run that filled `store` left it with: the sequence policy's
    /// earlier queries (the newest stored descriptors) and temporal consistency's held-back matches,
    /// where stored after the newest keyframe (a run with consistency off since leaves an older one,
    /// which no longer applies).
    fn resume_detector(&mut self, store: &KeyframeStore) -> Result<()> {
        let earlier_queries = self.params.detector().sequence_length.saturating_sub(1);
        let newest = store.last_keyframes(earlier_queries.max(1))?;
        let newest_id = newest.last().map(|k| k.0);
        let older = newest.len().saturating_sub(earlier_queries);
        let recent: Vec<Vec<f32>> = newest.into_iter().skip(older).map(|(_, _, descriptor)| descriptor).collect();
        // An unreadable state costs only the loops it held back: the keyframes load regardless.
        let consistency = match store.consistency()? {
            Some((id, json)) if newest_id == Some(id) => serde_json::from_str(&json)
                .map_err(|e| {
                    log::warn!(
                        "keyframe database {}: keyframe {id}'s temporal consistency state does not decode ({e}); \
                         consistency starts afresh",
                        store.path().display()
                    )
                })
                .ok(),
            _ => None,
        };
        self.detector.resume(&recent, consistency);
        Ok(())
    }

    pub fn store(&self) -> Option<&KeyframeStore> {
        self.store.as_ref()
    }

    /// The descriptor of one image, with no selection and no database.
    pub fn describe(&mut self, image: &RgbImage) -> Result<Vec<f32>> {
        let feature_map = self.embedder.feature_map(image)?;
        self.compute_descriptor(&feature_map)
    }

    /// Use stock candle ops instead of the fast kernels (verification).
    pub fn set_reference(&mut self, reference: bool) {
        self.embedder.set_reference(reference);
    }

    /// A keyframe whose id the tracker chose: no selection, always inserted.
    pub fn process_keyframe(&mut self, id: u64, stamp: Stamp, image: &RgbImage) -> Result<Outcome> {
        self.process_input(&Input::keyframe(id, stamp, image))
    }

    /// A plain frame: keyframe selection decides; accepted frames get `id`.
    pub fn process_frame(&mut self, id: u64, stamp: Stamp, image: &RgbImage) -> Result<Outcome> {
        self.next_id = self.next_id.max(id.saturating_add(1));
        self.run(id, true, &Input::frame(stamp, image))
    }

    /// A frame from a source: selection decides, its index is the id, its depth image (if any)
    /// gives verification a metric pose and its tracker pose (if any, camera-to-world) an odometry
    /// consistency check.
    pub fn process_source_frame(
        &mut self,
        frame: &Frame,
        tracker_pose: Option<nalgebra::Isometry3<f64>>,
    ) -> Result<Outcome> {
        let id = frame.index as u64;
        self.next_id = self.next_id.max(id.saturating_add(1));
        let input = Input { depth: frame.depth.as_ref(), tracker_pose, ..Input::frame(frame.stamp, &frame.image) };
        self.run(id, true, &input)
    }

    /// A plain frame with the id taken from the pipeline's counter.
    pub fn process_counted(&mut self, stamp: Stamp, image: &RgbImage) -> Result<Outcome> {
        self.process_input(&Input::frame(stamp, image))
    }

    /// What the node receives ([`Input`]): a tracker's keyframe or a plain frame, whose id then comes
    /// from the pipeline's counter.
    pub fn process_input(&mut self, input: &Input) -> Result<Outcome> {
        let (id, select) = match input.id {
            Some(id) => (id, false),
            None => (self.next_id, true),
        };
        self.next_id = self.next_id.max(id.saturating_add(1));
        self.run(id, select, input)
    }

    /// The camera frame and tracker pose stored with the keyframes of the history (those the
    /// detector searches), oldest first; empty without a store.
    pub fn stored_frames(&self) -> Result<Vec<(u64, (String, Option<nalgebra::Isometry3<f64>>))>> {
        match &self.store {
            Some(store) => store.frames(self.detector.db().len()),
            None => Ok(Vec::new()),
        }
    }

    /// Gives keyframe `id` its depth image after the fact (it arrived after the keyframe was
    /// processed), for verifying later queries against it; returns whether it was taken (false when
    /// verification is off, the keyframe's features are not kept, or it already has depth).
    pub fn attach_depth(&mut self, id: u64, depth: &DepthImage) -> Result<bool> {
        let Some(verifier) = &mut self.verifier else { return Ok(false) };
        let taken = verifier.attach_depth(id, depth)?;
        if let (true, Some(store), Some(features)) = (taken, &mut self.store, verifier.features(id)) {
            store.update_local_features(id, &features.to_bytes())?;
        }
        Ok(taken)
    }

    /// Gives verification the stored local features of the newest keyframes it keeps, so loops to
    /// keyframes stored before a restart are verified as before it.
    fn restore_local_features(&mut self) -> Result<()> {
        let (Some(store), Some(verifier)) = (&self.store, &mut self.verifier) else { return Ok(()) };
        let stored = store.local_features(verifier.params().keyframes)?;
        let count = stored.len();
        let mut other_kind = 0;
        for (id, bytes) in stored {
            let features = LocalFeatures::from_bytes(&bytes)
                .with_context(|| format!("keyframe {id}'s local features in {}", store.path().display()))?;
            other_kind += usize::from(features.descriptors.kind() != verifier.params().local_features);
            verifier.remember(id, features);
        }
        log::info!("keyframe database {}: local features of {count} keyframes restored", store.path().display());
        // Keyframes stored without features (by a run with verification off) cannot be checked.
        let stored_keyframes = store.len() as usize;
        let wanted = match verifier.params().keyframes {
            0 => stored_keyframes,
            kept => stored_keyframes.min(kept),
        };
        if count < wanted {
            log::warn!(
                "keyframe database {}: {} of its newest {wanted} keyframes have no local features (stored with \
                 verification off?); candidates that match them fail verification",
                store.path().display(),
                wanted - count
            );
        }
        if other_kind > 0 {
            log::warn!(
                "keyframe database {}: {other_kind} keyframes hold features of the other verification.local_features; \
                 candidates that match them fail verification",
                store.path().display()
            );
        }
        Ok(())
    }

    fn run(&mut self, id: u64, select: bool, input: &Input) -> Result<Outcome> {
        self.watch_stamps(input.stamp);
        // Every frame with a pose lengthens the tracker's path, keyframe or not.
        let tracked = input.tracker_pose.map(|pose| self.odometry.advance(&pose));
        // Before selection, so that a blank frame does not take a keyframe's turn.
        let contrast = contrast(input.image);
        if contrast < MIN_CONTRAST {
            if let Some(n) = self.blank_frames.occurred() {
                log::warn!(
                    "frame stamped {} shows nothing (grey levels vary by {contrast:.2}, under {MIN_CONTRAST}): no \
                     keyframe, no match ({n} such frames so far; a covered lens, darkness?)",
                    input.stamp
                );
            }
            return Ok(Outcome::default());
        }
        if select && self.selector.offer(input.stamp) == Verdict::Reject {
            return Ok(Outcome::default());
        }
        self.watch_frame_size(input.image);
        let fitting = Input { depth: self.fitting_depth(input.depth, input.image), ..*input };
        let input = &fitting;
        // The workers stay hot from the forward pass through the search (its probed lists are
        // scanned in parallel). During a `--db` append (an fsynced transaction) a poller gives up
        // after `runtime::HOT_WORKER_PATIENCE`.
        crate::runtime::with_hot_workers(|| self.describe_and_detect(id, select, input, tracked))
    }

    /// Selection and the exclusion of recent keyframes go by stamps, so frames whose stamps do not
    /// advance (all 0 from a tracker on `use_sim_time` with no `/clock`, a bag written without header
    /// stamps) are mostly dropped or never matched: the first and every hundredth is named in the log.
    fn watch_stamps(&mut self, stamp: Stamp) {
        match self.newest_stamp {
            Some(newest) if stamp <= newest => {
                if let Some(n) = self.stamps_not_advancing.occurred() {
                    log::warn!(
                        "a frame stamped {stamp} came after one stamped {newest}: keyframe selection \
                         (selection.min_period) and the exclusion of recent keyframes \
                         (detector.exclude_recent.seconds) go by stamps, so frames that do not advance are \
                         mostly dropped or never matched ({n} such frames so far; a tracker on use_sim_time \
                         without /clock stamps 0)"
                    );
                }
            }
            _ => self.newest_stamp = Some(stamp),
        }
    }

    /// Verification's intrinsics hold for the size they were calibrated at; frames that are those
    /// images resized are verified with them scaled ([`Intrinsics::for_image`]), said once per size,
    /// and frames of another shape without them (no pose), the first and every hundredth named.
    fn watch_frame_size(&mut self, image: &RgbImage) {
        let Some(intrinsics) = self.verifier.as_ref().and_then(|v| v.params().intrinsics) else { return };
        let size = [image.width(), image.height()];
        match (intrinsics.size, intrinsics.for_image(size)) {
            (Some([width, height]), Some(scaled)) if scaled != intrinsics && self.scaled_to != Some(size) => {
                self.scaled_to = Some(size);
                log::info!(
                    "the camera intrinsics are for {width}x{height} images, the frames are {}x{}: scaled to fx {:.1} \
                     fy {:.1} cx {:.1} cy {:.1}",
                    size[0],
                    size[1],
                    scaled.fx,
                    scaled.fy,
                    scaled.cx,
                    scaled.cy
                );
            }
            (Some([width, height]), None) => {
                if let Some(n) = self.misfit_sizes.occurred() {
                    log::warn!(
                        "the camera intrinsics are for {width}x{height} images, a frame is {}x{}, which no \
                         scaling of them describes: its loops are verified without intrinsics, with no relative \
                         pose ({n} such frames so far; are the intrinsics this camera's, for this image topic?)",
                        size[0],
                        size[1]
                    );
                }
            }
            _ => {}
        }
    }

    /// `depth` where it has `image`'s size. One of another size cannot be registered to it (another
    /// camera, or a depth topic not registered to the colour one): the frame goes on without it, and
    /// the first and every hundredth such image is named in the log.
    fn fitting_depth<'a>(&mut self, depth: Option<&'a DepthImage>, image: &RgbImage) -> Option<&'a DepthImage> {
        let depth = depth?;
        if (depth.width, depth.height) == image.dimensions() {
            return Some(depth);
        }
        if let Some(n) = self.misfit_depths.occurred() {
            log::warn!(
                "a depth image is {}x{}, its colour image {}x{}; the frame goes on without depth ({n} such \
                 depth images so far; is the depth registered to the colour camera?)",
                depth.width,
                depth.height,
                image.width(),
                image.height()
            );
        }
        None
    }

    fn describe_and_detect(
        &mut self,
        id: u64,
        select: bool,
        input: &Input,
        tracked: Option<Tracked>,
    ) -> Result<Outcome> {
        let Input { stamp, image, depth, .. } = *input;
        let mut outcome = Outcome::default();
        let start = Instant::now();
        // With verification, the local features are extracted beside the forward pass: its parallel
        // regions leave a worker idle between them, and the features need only the image. Not when
        // the selector may still reject the keyframe by its descriptor.
        let overlap = !(select && self.selector.needs_descriptor());
        let (feature_map, early_features) = match (&self.verifier, overlap) {
            (Some(verifier), true) => {
                let embedder = &mut self.embedder;
                let (map, (features, ms)) = rayon::join(
                    || embedder.feature_map(image),
                    || {
                        let started = Instant::now();
                        (verifier.extract(image, depth), started.elapsed().as_secs_f64() * 1e3)
                    },
                );
                (map?, Some((features?, ms)))
            }
            _ => (self.embedder.feature_map(image)?, None),
        };
        let after_network = Instant::now();
        let descriptor = self.compute_descriptor(&feature_map)?;
        let after_descriptor = Instant::now();
        outcome.timings.network_ms = (after_network - start).as_secs_f64() * 1e3;
        outcome.timings.descriptor_ms = (after_descriptor - after_network).as_secs_f64() * 1e3;
        if select && self.selector.needs_descriptor() && !self.selector.offer_descriptor(stamp, &descriptor)? {
            return Ok(outcome);
        }
        // Refused before the detector sees it, as the store would refuse it after: an id names one
        // keyframe, so a second one under it would send later loops to the wrong place.
        if let Some(store) = &self.store {
            ensure!(!store.contains(id)?, "keyframe id {id} is already stored in {}", store.path().display());
        }
        ensure!(
            !self.taken_ids.contains(&id),
            "keyframe id {id} was taken by an earlier keyframe (a tracker that restarts its ids needs a new session)"
        );
        // Extracted before the keyframe enters the detector, so that a failure leaves no trace of it.
        let features = match (early_features, &self.verifier) {
            (Some(early), _) => Some(early),
            (None, Some(_)) => {
                let started = Instant::now();
                Some((self.local_features(image, depth)?, started.elapsed().as_secs_f64() * 1e3))
            }
            (None, None) => None,
        };
        let before_detector = Instant::now();
        // With verification, alternatives to try when a better match fails.
        let (nearest, candidates) = self.detector.process_ranked(id, stamp, &descriptor, self.matches_tried())?;
        self.taken_ids.insert(id);
        (outcome.best, outcome.candidates) = (nearest.first().copied(), candidates);
        outcome.keyframe = Some(id);
        if let Some(tracked) = tracked {
            self.odometry.keep(id, tracked);
        }
        // Earlier keyframes' loops that temporal consistency held back and this keyframe's confirm
        // (with verification, after it: only verified loops confirm).
        if self.verifier.is_none() {
            let top_k = self.params.detector().top_k;
            let confirmed = self.detector.confirm_held_back(id, &outcome.candidates, top_k);
            outcome.candidates.splice(0..0, confirmed);
        }
        let after_detector = Instant::now();
        outcome.timings.detector_ms = (after_detector - before_detector).as_secs_f64() * 1e3;
        let mut stored_features = None;
        if let Some((features, extraction_ms)) = features {
            self.verify_outcome(&features, tracked, &nearest, &mut outcome);
            let confirmed = self.detector.confirm_held_back(id, &outcome.candidates, self.matches_tried());
            let confirmed = self.verify_confirmed(confirmed, &mut outcome);
            for c in &confirmed {
                self.detector.set_reported(c.query_id, c.rank as usize + 1);
            }
            outcome.candidates.splice(0..0, confirmed);
            outcome.unchecked_by_odometry = self.watch_unchecked_loops(&outcome.candidates);
            if self.store.is_some() {
                stored_features = Some(features.to_bytes());
            }
            self.remember_features(id, features);
            outcome.timings.verification_ms = extraction_ms + after_detector.elapsed().as_secs_f64() * 1e3;
        }
        // The keyframe, its final candidates and its local features in one transaction, before any
        // caller writes the candidates out: a restart finds all or none.
        if let Some(store) = &mut self.store {
            let consistency =
                self.detector.consistency_state().map(|state| serde_json::to_string(&state)).transpose()?;
            store.append_keyframe(&KeyframeRecord {
                id,
                stamp,
                descriptor: &descriptor,
                candidates: &outcome.candidates,
                local_features: stored_features.as_deref(),
                frame_id: input.frame_id,
                tracker_pose: input.tracker_pose,
                consistency: consistency.as_deref(),
            })?;
        }
        Ok(outcome)
    }

    /// How many inputs so far were well formed but could not be used as they came.
    pub fn input_problems(&self) -> InputProblems {
        InputProblems {
            stamps_not_advancing: self.stamps_not_advancing.count(),
            blank_frames: self.blank_frames.count(),
            misfit_depths: self.misfit_depths.count(),
            misfit_sizes: self.misfit_sizes.count(),
        }
    }

    /// Whether [`Outcome::best_verified`] is worked out when the best match is not a candidate (on by
    /// default, for evaluation; off, it is `None` then).
    pub fn set_verify_best(&mut self, verify_best: bool) {
        self.verify_best = verify_best;
    }

    /// Whether geometric verification is on.
    pub fn verifies(&self) -> bool {
        self.verifier.is_some()
    }

    /// How many of a keyframe's nearest matches verification checks (`verification.candidates`; 1
    /// when verification is off).
    pub fn matches_tried(&self) -> usize {
        self.verifier.as_ref().map_or(1, |v| v.params().candidates)
    }

    /// The local features of `image` (with keypoint depths from `depth`, where it has the image's
    /// size) for verification (empty when verification is off).
    pub fn local_features(&mut self, image: &RgbImage, depth: Option<&DepthImage>) -> Result<LocalFeatures> {
        self.watch_frame_size(image);
        let depth = self.fitting_depth(depth, image);
        match &self.verifier {
            Some(verifier) => verifier.extract(image, depth),
            None => Ok(LocalFeatures::default()),
        }
    }

    /// Keeps `features` as keyframe `id`'s for later verification (nothing when verification is off).
    pub fn remember_features(&mut self, id: u64, features: LocalFeatures) {
        if let Some(verifier) = &mut self.verifier {
            verifier.remember(id, features);
        }
    }

    /// Checks `features` against keyframe `id`; `None` when verification is off. A keyframe whose
    /// features are not kept fails (it cannot be checked).
    pub fn verify(&self, features: &LocalFeatures, id: u64) -> Option<Verification> {
        let verifier = self.verifier.as_ref()?;
        Some(verifier.verify(features, id).unwrap_or(Verification {
            matches: 0,
            inliers: 0,
            model: None,
            accepted: false,
            pose: None,
        }))
    }

    /// [`Pipeline::verify`], then, where the features pass, the odometry check of the query keyframe
    /// (tracked at `query`): the verification (not accepted where either check failed it) and whether
    /// the odometry check failed it.
    fn verify_with_odometry(
        &self,
        features: &LocalFeatures,
        query: Option<Tracked>,
        matched: u64,
    ) -> (Verification, bool) {
        let mut v = self.verify(features, matched).expect("called with verification on");
        let odometry_failed = v.accepted && !self.odometry_consistent(query, matched, v.pose.as_ref());
        v.accepted &= !odometry_failed;
        (v, odometry_failed)
    }

    /// Names loops reported without the odometry check it was set to make, because one of their
    /// keyframes has no tracker pose while others have: a tracker that sends poses for some frames
    /// only, or a database continued with `--poses` on one run and not the other. (With no pose at
    /// all, nothing is checked, and the replay's summary says so.)
    /// Returns how many of `reported` those are.
    fn watch_unchecked_loops(&mut self, reported: &[LoopCandidate]) -> usize {
        let checks = self.verifier.as_ref().and_then(|v| v.params().drift).is_some();
        if !checks || self.odometry.is_empty() {
            return 0;
        }
        let mut unchecked = 0;
        for c in reported {
            let Some(untracked) = [c.query_id, c.match_id].into_iter().find(|&id| self.odometry.tracked(id).is_none())
            else {
                continue;
            };
            unchecked += 1;
            if let Some(n) = self.unchecked_loops.occurred() {
                log::warn!(
                    "loop {} -> {} was reported without the odometry check: keyframe {untracked} has no tracker \
                     pose, while {} keyframes have one ({n} such loops so far; poses for some frames only, or a \
                     database continued with --poses on one run and not the other?)",
                    c.query_id,
                    c.match_id,
                    self.odometry.len()
                );
            }
        }
        unchecked
    }

    /// Whether a loop from the query (tracked at `query`) to keyframe `matched`, verified with
    /// relative pose `pose`, fits the tracker's trajectory; true when not checked (no drift bound, or
    /// either keyframe without a pose).
    fn odometry_consistent(&self, query: Option<Tracked>, matched: u64, pose: Option<&RelativePose>) -> bool {
        let bound = self.verifier.as_ref().and_then(|v| v.params().drift);
        let (Some(bound), Some(query)) = (bound, query) else { return true };
        match self.odometry.check(query, matched, pose.map(|pose| &pose.rotation), &bound) {
            Some(check) if !check.consistent() => {
                let rotation = check.rotation_deg.map(|deg| format!(", relative rotations {deg:.1} deg apart"));
                log::debug!(
                    "loop to keyframe {matched} rejected by odometry: tracked {:.2} m apart after {:.2} m travelled{}",
                    check.distance_m,
                    check.path_m,
                    rotation.unwrap_or_default()
                );
                false
            }
            _ => true,
        }
    }

    /// Verifies the candidates best first and keeps the first `detector.top_k` that pass verification
    /// and odometry consistency; those that fail before them are dropped (counted in
    /// [`Outcome::rejected`]), those after them are not tried. With [`Pipeline::set_verify_best`] the
    /// best match becomes the first of `nearest` that passes (else the nearest, marked failed).
    fn verify_outcome(
        &self,
        features: &LocalFeatures,
        tracked: Option<Tracked>,
        nearest: &[Match],
        outcome: &mut Outcome,
    ) {
        // Per match id: the feature check, and whether the odometry check (made only on what the
        // features verified) failed.
        let mut checked: Vec<(u64, Verification, bool)> = Vec::new();
        let mut check = |id: u64| -> (Verification, bool) {
            if let Some(&(_, v, odometry_failed)) = checked.iter().find(|(seen, ..)| *seen == id) {
                return (v, odometry_failed);
            }
            let (v, odometry_failed) = self.verify_with_odometry(features, tracked, id);
            checked.push((id, v, odometry_failed));
            (v, odometry_failed)
        };
        let best_is_candidate =
            outcome.best.is_some_and(|best| outcome.candidates.iter().any(|c| c.match_id == best.id));
        if self.verify_best {
            let verifications: Vec<_> = nearest.iter().map(|m| Some(check(m.id).0)).collect();
            let min_score = self.detector.min_score();
            let passes: Vec<bool> = nearest.iter().map(|m| m.score >= min_score).collect();
            if let Some(chosen) = best_supported_passing(&verifications, &passes) {
                outcome.best = Some(nearest[chosen]);
            }
        }
        // Every candidate is checked; those verified are reported most inliers first
        // ([`best_supported`]).
        outcome.candidates.sort_by_key(|c| std::cmp::Reverse(check(c.match_id).0.support()));
        if self.verify_best || best_is_candidate {
            outcome.best_verified = outcome.best.map(|best| check(best.id).0.accepted);
        }
        let wanted = self.params.detector().top_k;
        let (mut kept, mut rejected, mut odometry_rejected) = (0, 0, 0);
        outcome.candidates.retain_mut(|c| {
            if kept == wanted {
                return false;
            }
            let (v, odometry_failed) = check(c.match_id);
            odometry_rejected += odometry_failed as usize;
            if !v.accepted && !odometry_failed {
                log::debug!(
                    "candidate {} -> {} rejected by verification: {} inliers of {} matches",
                    c.query_id,
                    c.match_id,
                    v.inliers,
                    v.matches
                );
            }
            if v.accepted {
                c.verified = Some(Verified { inliers: v.inliers as u32, pose: v.pose });
                kept += 1;
            } else {
                rejected += 1;
            }
            v.accepted
        });
        outcome.rejected = rejected;
        outcome.rejected_by_odometry = odometry_rejected;
        for (rank, candidate) in outcome.candidates.iter_mut().enumerate() {
            candidate.rank = rank as u32;
        }
    }

    /// Verifies loops of earlier keyframes that temporal consistency held back and the current
    /// keyframe confirmed (grouped by keyframe, each ranked after what it already reported), with the
    /// local features and tracker pose kept for their own keyframes; of those that pass, most inliers
    /// first until a keyframe has `detector.top_k`. Returns those, ranked on, and counts the failed in
    /// `outcome`.
    fn verify_confirmed(&self, confirmed: Vec<LoopCandidate>, outcome: &mut Outcome) -> Vec<LoopCandidate> {
        let verifier = self.verifier.as_ref().expect("called with verification on");
        let wanted = self.params.detector().top_k as u32;
        let mut kept: Vec<LoopCandidate> = Vec::new();
        // A keyframe's released matches come together, ranked after those it already reported.
        for released in confirmed.chunk_by(|a, b| a.query_id == b.query_id) {
            let first_rank = released[0].rank;
            if first_rank >= wanted {
                continue;
            }
            let mut passed: Vec<LoopCandidate> = Vec::new();
            for c in released {
                let checked = verifier
                    .features(c.query_id)
                    .map(|features| self.verify_with_odometry(features, self.odometry.tracked(c.query_id), c.match_id));
                let Some((v, _)) = checked.filter(|(v, _)| v.accepted) else {
                    log::debug!("held-back candidate {} -> {} rejected by verification", c.query_id, c.match_id);
                    outcome.rejected += 1;
                    outcome.rejected_by_odometry += usize::from(checked.is_some_and(|(_, odometry)| odometry));
                    continue;
                };
                log::debug!("held-back candidate {} -> {} confirmed and verified", c.query_id, c.match_id);
                passed.push(LoopCandidate {
                    verified: Some(Verified { inliers: v.inliers as u32, pose: v.pose }),
                    ..c.clone()
                });
            }
            // Most inliers first, as for a keyframe's own candidates ([`best_supported`]).
            passed.sort_by_key(|c| std::cmp::Reverse(c.verified.map(|v| v.inliers)));
            for (rank, c) in (first_rank..wanted).zip(passed) {
                kept.push(LoopCandidate { rank, ..c });
            }
        }
        kept
    }

    /// Changes one parameter at run time, validated by [`Params::set_at_runtime`]: a bad value
    /// is refused with a reason and the old value stays. `arch`, `input_size` and
    /// `descriptor.mode` are fixed at start (stored descriptors would no longer be comparable).
    pub fn set_param(&mut self, name: &str, value: ParamValue) -> std::result::Result<(), ParamError> {
        self.params.set_at_runtime(name, value)?;
        self.detector.set_params(self.params.detector());
        self.selector.set_params(self.params.selection());
        if let (Some(verifier), Some(params)) = (&mut self.verifier, self.params.verification(self.camera_info)) {
            verifier.set_params(params);
        }
        Ok(())
    }

    /// Intrinsics from the camera driver (a node's `camera_info`). They apply when the `camera.*`
    /// parameters give none; with `verification.mode auto` the first ones turn verification on, for
    /// the keyframes from then on (earlier keyframes have no local features, so a candidate that
    /// matches one of them is rejected). Returns whether verification is on afterwards.
    pub fn set_camera_info(&mut self, intrinsics: Intrinsics) -> Result<bool> {
        self.camera_info = Some(intrinsics);
        // New values: the next scaled ones are said again.
        self.scaled_to = None;
        if let Some(params) = self.params.verification(self.camera_info) {
            match &mut self.verifier {
                Some(verifier) => verifier.set_params(params),
                None => {
                    log::info!("geometric verification on, with the camera intrinsics now known: {params:?}");
                    self.verifier = Some(Verifier::new(params)?);
                    self.restore_local_features()?;
                }
            }
        }
        Ok(self.verifier.is_some())
    }
}
