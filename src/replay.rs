//! Replaying a source offline: every frame through one [`Pipeline`], in order, with keyframe
//! selection, collecting candidates, the best match of each keyframe (for evaluation) and timings.
//! `replay`, `eval` and `demo` share this loop.
//!
//! Resuming: when the pipeline has a keyframe store attached, frames whose index (= keyframe id) is at
//! most the largest stored id were processed by an earlier run and are skipped (counted in
//! [`ReplayRun::skipped`]); keyframe selection goes on from the newest stored keyframe
//! ([`Pipeline::attach_store`]), so the restarted run selects the frames an uninterrupted one would.
//! The newest stored keyframe must be the source's frame of the same index, stamp and image: a
//! database is continued only with the source it was built from.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use crate::config::ParamValue;
use crate::detector::store::{is_keyframe_store, KeyframeStore};
use crate::detector::{sequence, walk, Detector, Match};
use crate::eval::QueryResult;
use crate::io::tum::TrackerPoses;
use crate::io::{open_source_topics, unreadable_frame, Topics, UnreadableFrames};
use crate::pipeline::{Pipeline, Timings};
use crate::types::{LoopCandidate, Stamp, Verified};
use crate::verification::best_supported_passing;

/// One keyframe of a replay.
#[derive(Clone, Debug)]
pub struct ReplayedKeyframe {
    /// Frame index in the source (also the keyframe id).
    pub index: usize,
    pub stamp: Stamp,
    /// Nearest eligible earlier keyframe, threshold aside.
    pub best: Option<Match>,
    /// Whether `best` passed geometric verification (`None`: verification off or no match).
    pub best_verified: Option<bool>,
}

/// Everything a replay produced.
#[derive(Debug, Default)]
pub struct ReplayRun {
    /// Frames read from the source.
    pub frames: usize,
    /// Frames skipped because an attached store already holds their keyframe ids (module doc).
    pub skipped: usize,
    /// Stamps of all frames read, in replay order.
    pub frame_stamps: Vec<Stamp>,
    pub keyframes: Vec<ReplayedKeyframe>,
    pub candidates: Vec<LoopCandidate>,
    /// Candidates that passed the threshold but failed geometric verification.
    pub rejected: usize,
    /// Of `rejected`, those the odometry check rejected (`verification.max_drift`).
    pub rejected_by_odometry: usize,
    /// Candidates reported without the odometry check it was set to make (a keyframe without a pose).
    pub unchecked_by_odometry: usize,
    /// Summed per-stage time over the keyframes.
    pub total: Timings,
    pub wall_secs: f64,
    /// Frames read whose image could not be decoded, skipped (counted in `frames`).
    pub unreadable: UnreadableFrames,
    /// Set when the source broke off (e.g. a truncated bag) after the frames above.
    pub error: Option<String>,
}

impl ReplayRun {
    /// Mean per-stage milliseconds per keyframe.
    pub fn mean(&self) -> Timings {
        let n = self.keyframes.len().max(1) as f64;
        let t = &self.total;
        Timings {
            network_ms: t.network_ms / n,
            descriptor_ms: t.descriptor_ms / n,
            detector_ms: t.detector_ms / n,
            verification_ms: t.verification_ms / n,
        }
    }

    /// [`ReplayRun::mean`] by name (for summaries and JSON).
    pub fn mean_timings(&self) -> Vec<(&'static str, f64)> {
        let t = self.mean();
        vec![
            ("network_ms", t.network_ms),
            ("descriptor_ms", t.descriptor_ms),
            ("detector_ms", t.detector_ms),
            ("verification_ms", t.verification_ms),
        ]
    }

    /// Why no keyframe could be matched at all, where that is so: the recency rules and the minimum
    /// history (`params`) left no eligible keyframe for any query, most often a sequence shorter than
    /// `detector.exclude_recent.seconds`. `None` where some keyframe had one, or none was replayed.
    pub fn why_nothing_could_match(&self, params: &crate::config::Params) -> Option<String> {
        let (first, last) = (self.keyframes.first()?, self.keyframes.last()?);
        if self.keyframes.iter().any(|k| k.best.is_some()) {
            return None;
        }
        let detector = params.detector();
        if let Some(why) = detector.never_matches() {
            return Some(format!("no keyframe could be matched: {why}"));
        }
        let span = (last.stamp.nanos - first.stamp.nanos) as f64 / 1e9;
        Some(format!(
            "no keyframe could be matched: a match must be at least detector.exclude_recent.seconds ({} s) and \
             detector.exclude_recent.count ({}) keyframes older than its query, after detector.min_history ({}) \
             keyframes, and these {} keyframes span {span:.1} s; for a short sequence lower them (e.g. --param \
             detector.exclude_recent.seconds=5)",
            detector.exclude_recent_secs,
            detector.exclude_recent_count,
            detector.min_history,
            self.keyframes.len(),
        ))
    }

    /// One evaluation result per keyframe: its frame index, and its best match's frame index and score.
    /// A best match that failed geometric verification counts as no match.
    pub fn query_results(&self) -> Vec<QueryResult> {
        self.keyframes
            .iter()
            .map(|k| QueryResult {
                query: k.index,
                best: k.best.filter(|_| k.best_verified != Some(false)).map(|m| (m.id as usize, m.score)),
            })
            .collect()
    }

    /// [`ReplayRun::query_results`] from what was reported: each keyframe's best candidate after the
    /// whole policy (threshold, temporal consistency, verification), or no match. Evaluation's best
    /// match ignores the threshold and consistency; this scores the policy as a node applies it.
    pub fn reported_results(&self) -> Vec<QueryResult> {
        let best: std::collections::HashMap<u64, &LoopCandidate> =
            self.candidates.iter().filter(|c| c.rank == 0).map(|c| (c.query_id, c)).collect();
        self.keyframes
            .iter()
            .map(|k| QueryResult {
                query: k.index,
                best: best.get(&(k.index as u64)).map(|c| (c.match_id as usize, c.score)),
            })
            .collect()
    }
}

/// What the database/query mode produced ([`run_database_queries`]).
#[derive(Debug, Default)]
pub struct DatabaseQueriesRun {
    /// One result per query, in query order.
    pub results: Vec<QueryResult>,
    /// With verification, each query's reported match's: its inliers and relative pose (`None`
    /// without verification, and where no match passed).
    pub verified: Vec<Option<Verified>>,
    /// The id and stamp of every database frame, in database order: a source's frame index, or a
    /// keyframe database's keyframe id (what the results name).
    pub database: Vec<(u64, Stamp)>,
    /// The stamps of the queries, in their order (a query's index is its position here), unreadable
    /// ones' too.
    pub query_stamps: Vec<Stamp>,
    /// Database frames skipped because their images could not be decoded (none is in `database`).
    pub unreadable_database: UnreadableFrames,
    /// Queries skipped because their images could not be decoded (none is in `results`).
    pub unreadable_queries: UnreadableFrames,
    /// Milliseconds per image read and described, database and queries together (a keyframe
    /// database's keyframes are loaded, not described, and not counted).
    pub per_image_ms: f64,
    /// Set when a source broke off (a truncated bag, a damaged chunk): the frames before it
    /// were matched, and this names the source and what went wrong.
    pub error: Option<String>,
}

impl DatabaseQueriesRun {
    /// The timings by name (for summaries and JSON).
    pub fn timings(&self) -> Vec<(&'static str, f64)> {
        vec![("per_image_ms", self.per_image_ms)]
    }
}

/// Whether `source` is a bag (what the image topic of the database/query mode applies to).
fn is_bag(source: &Path) -> bool {
    !crate::io::is_image_folder(source) && !source.join("rgb.txt").is_file() && !is_keyframe_store(source)
}

/// The topics to open `source` with in the database/query mode, from those given (`topics`): the
/// image topic applies to bags only (the same camera's topic in both), the depth topic to the
/// database's bag only (`with_depth`), and poses to neither.
fn database_query_topics(source: &Path, topics: &Topics, with_depth: bool) -> Topics {
    let bag = is_bag(source);
    Topics {
        image: topics.image.clone().filter(|_| bag),
        depth: topics.depth.clone().filter(|_| bag && with_depth),
        poses: None,
    }
}

/// Database/query mode: every frame of `database` is stored, then each frame of `queries` is
/// matched against them all (no recency rules: the two are different visits). Each is any source
/// [`open_source_topics`] opens (image folder in name order, TUM folder, ROS 1 or ROS 2 bag;
/// `topics.image` the image topic of bags), a frame's index its position in its source; the database
/// may also be a keyframe database (`--db`, [`Pipeline::load_map`]), its keyframes named by their
/// ids. The database's depth images (a TUM folder's `depth.txt`, a bag's `topics.depth`) give
/// verified matches metric poses,
/// and the camera intrinsics a source carries (the database's, else the queries') turn
/// verification on as in a replay. A frame whose image does not decode is skipped
/// ([`DatabaseQueriesRun::unreadable_database`], [`DatabaseQueriesRun::unreadable_queries`]). A
/// source that breaks off (a truncated bag, a damaged chunk)
/// ends the reading ([`DatabaseQueriesRun::error`]): the queries read before are matched, and none
/// where the database broke off. With the default `detector.sequence.length` 0, queries that look like a walk
/// ([`walk::why_not_a_walk`]) are aligned with the database as a whole walk ([`walk::align_walk`]; a
/// match's score then also weighs how sure the place is, and `detector.sequence.length` stays 0),
/// others matched as single images (the length is set to 1); a length
/// set above 1 scores windows of that many queries ([`sequence`]), a walk's first queries taking
/// later ones into their window ([`sequence::queries_ahead`]). Either way every query is described
/// before any is matched (their descriptors are kept meanwhile, 11.25 KiB each for the default); with
/// verification the queries are read a second time for their local features.
pub fn run_database_queries(
    pipeline: &mut Pipeline,
    database: &Path,
    queries: &Path,
    topics: &Topics,
    progress: bool,
) -> Result<DatabaseQueriesRun> {
    for rule in ["detector.min_history", "detector.exclude_recent.count"] {
        pipeline.set_param(rule, ParamValue::Integer(0)).map_err(anyhow::Error::msg)?;
    }
    pipeline.set_param("detector.exclude_recent.seconds", ParamValue::Double(0.0)).map_err(anyhow::Error::msg)?;
    if topics.image.is_some() && !is_bag(database) && !is_bag(queries) {
        bail!("--topic names the image topic of a bag, and neither the database nor the queries is one");
    }
    if topics.depth.is_some() && !is_bag(database) {
        bail!("--depth-topic names the depth topic of the database's bag, and the database is not a bag");
    }
    ensure!(topics.poses.is_none(), "tracker poses apply to a replayed source, not to a database and queries");
    let open = |source: &Path, with_depth: bool| {
        open_source_topics(source, &database_query_topics(source, topics, with_depth))
    };
    let query_frames = open(queries, false)?;
    let started = Instant::now();
    let mut run = DatabaseQueriesRun::default();
    let bar = frames_bar(progress, query_frames.len_hint().unwrap_or(0));
    let map_from_store = is_keyframe_store(database);
    if map_from_store {
        log::info!("queries: {}", query_frames.describe());
        adopt_carried_intrinsics(pipeline, query_frames.intrinsics())?;
        pipeline.load_map(KeyframeStore::open_read_only(database)?)?;
        let db = pipeline.detector().db();
        run.database = (0..db.len()).map(|p| (db.id(p), db.stamp(p))).collect();
    } else {
        let database_frames =
            open(database, true).context("reading the database (a source, or a keyframe database made with --db)")?;
        bar.inc_length(database_frames.len_hint().unwrap_or(0) as u64);
        log::info!("database: {}; queries: {}", database_frames.describe(), query_frames.describe());
        adopt_carried_intrinsics(pipeline, database_frames.intrinsics().or_else(|| query_frames.intrinsics()))?;
        for frame in database_frames {
            let frame = match frame {
                Ok(frame) => frame,
                Err(e) => {
                    if let Some(unreadable) = unreadable_frame(&e) {
                        run.unreadable_database.skip(database, unreadable);
                        bar.inc(1);
                        continue;
                    }
                    run.error = Some(broke_off("the database", database, run.database.len(), &e));
                    break;
                }
            };
            let descriptor = pipeline.describe(&frame.image)?;
            let id = frame.index as u64;
            pipeline.detector_mut().insert(id, Stamp::from_nanos(frame.index as i64), &descriptor)?;
            let features = pipeline.local_features(&frame.image, frame.depth.as_ref())?;
            pipeline.remember_features(id, features);
            run.database.push((id, frame.stamp));
            bar.inc(1);
        }
    }
    if !map_from_store && run.database.is_empty() && run.unreadable_database.count() > 0 && run.error.is_none() {
        return Err(run.unreadable_database.none_readable(database, run.unreadable_database.count()));
    }
    // The readable queries' descriptors and indexes.
    let mut descriptors = Vec::new();
    let mut query_indexes = Vec::new();
    // Where the database broke off, no query is read: a walk would be aligned with part of the map.
    if run.error.is_none() {
        for frame in query_frames {
            match frame {
                Ok(frame) => {
                    descriptors.push(pipeline.describe(&frame.image)?);
                    query_indexes.push(run.query_stamps.len());
                    run.query_stamps.push(frame.stamp);
                    bar.inc(1);
                }
                Err(e) if unreadable_frame(&e).is_some() => {
                    let unreadable = unreadable_frame(&e).context("matched above")?;
                    run.unreadable_queries.skip(queries, unreadable);
                    run.query_stamps.push(unreadable.stamp);
                    bar.inc(1);
                }
                Err(e) => {
                    run.error = Some(broke_off("the queries", queries, run.query_stamps.len(), &e));
                    break;
                }
            }
        }
    }
    bar.finish_and_clear();
    if run.unreadable_queries.count() > 0 && descriptors.is_empty() && run.error.is_none() {
        return Err(run.unreadable_queries.none_readable(queries, run.query_stamps.len()));
    }
    let tried = pipeline.matches_tried();
    let aligned = if pipeline.params().get("detector.sequence.length") == Some(ParamValue::Integer(0)) {
        let aligned = walk_matches(pipeline.detector(), &descriptors, tried)?;
        if aligned.is_none() {
            // Single images: the length stays 0 only where the walk was aligned.
            pipeline.set_param("detector.sequence.length", ParamValue::Integer(1)).map_err(anyhow::Error::msg)?;
        }
        aligned
    } else {
        None
    };
    let length = match pipeline.params().get("detector.sequence.length") {
        Some(ParamValue::Integer(length)) => length.max(1) as usize,
        _ => 1,
    };
    // Read again for their local features: the query images are not all kept while their
    // descriptors are.
    let mut again = if pipeline.verifies() { Some(open(queries, false)?) } else { None };
    for (position, (descriptor, &index)) in descriptors.iter().zip(&query_indexes).enumerate() {
        let ahead = &descriptors[position + 1..][..sequence::queries_ahead(length, position, descriptors.len())];
        // With verification, the nearest verified with the most inliers, those passing the threshold
        // first ([`best_supported_passing`]); none verified counts as no match.
        let nearest = match &aligned {
            Some(aligned) => aligned[position].clone(),
            None => pipeline.detector_mut().query_ranked(Stamp::from_nanos(i64::MAX), descriptor, ahead, tried)?,
        };
        let best = match again.as_mut() {
            Some(frames) => {
                // Only the queries read the first time are matched, so these read again; the
                // unreadable ones are passed over again.
                let frame = loop {
                    let read =
                        frames.next().with_context(|| format!("{} ended early when read again", queries.display()))?;
                    match read {
                        Ok(frame) if frame.index == index => break frame,
                        Ok(frame) => ensure!(frame.index < index, "{} changed while it was read", queries.display()),
                        Err(e) if unreadable_frame(&e).is_some_and(|u| u.index < index) => {}
                        Err(e) => return Err(e.context(format!("reading the queries {} again", queries.display()))),
                    }
                };
                let features = pipeline.local_features(&frame.image, None)?;
                let verifications = nearest.iter().map(|m| {
                    let verification = pipeline.verify(&features, m.id);
                    if let Some(v) = verification {
                        log::debug!(
                            "query {index} -> database {} (score {:.3}): {} inliers of {} matches, {}",
                            m.id,
                            m.score,
                            v.inliers,
                            v.matches,
                            if v.accepted { "verified" } else { "rejected" }
                        );
                    }
                    verification
                });
                let verifications: Vec<_> = verifications.collect();
                let min_score = pipeline.detector().min_score();
                let passes: Vec<bool> = nearest.iter().map(|m| m.score >= min_score).collect();
                let chosen = best_supported_passing(&verifications, &passes);
                let verified = chosen.and_then(|i| verifications[i].as_ref());
                run.verified.push(verified.map(|v| Verified { inliers: v.inliers as u32, pose: v.pose }));
                chosen.map(|i| nearest[i])
            }
            None => {
                run.verified.push(None);
                nearest.first().copied()
            }
        };
        run.results.push(QueryResult { query: index, best: best.map(|m| (m.id as usize, m.score)) });
    }
    // The images described.
    let frames = if map_from_store { 0 } else { run.database.len() } + descriptors.len();
    run.per_image_ms = started.elapsed().as_secs_f64() * 1e3 / frames.max(1) as f64;
    Ok(run)
}

/// A progress bar over `frames` frames (0: not known), drawn only with `progress`.
fn frames_bar(progress: bool, frames: usize) -> ProgressBar {
    let bar = if progress { ProgressBar::new(frames as u64) } else { ProgressBar::hidden() };
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} frames, {per_sec}, {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// What a source that broke off after `read` frames says ([`DatabaseQueriesRun::error`]), on one line.
fn broke_off(what: &str, source: &Path, read: usize, error: &anyhow::Error) -> String {
    let error = format!("{error:#}");
    format!("{what} {} broke off after {read} frames: {}", source.display(), error.trim_end())
}

/// Hands the camera intrinsics a source carries to `pipeline`, unless the `camera.*` parameters
/// give them (logged either way).
fn adopt_carried_intrinsics(pipeline: &mut Pipeline, carried: Option<crate::io::SourceIntrinsics>) -> Result<()> {
    if let Some(carried) = carried {
        if pipeline.params().intrinsics().is_some() {
            log::info!("camera intrinsics from the camera.* parameters; {} not used", carried.origin);
        } else {
            log::info!("camera intrinsics from {}: {:?}", carried.origin, carried.intrinsics);
            pipeline.set_camera_info(carried.intrinsics)?;
        }
    }
    Ok(())
}

/// The default's walk alignment of `queries` (descriptors in their order) with every keyframe of
/// `detector`, each query's up to `depth` matches with the walk's score ([`walk`]); `None` where
/// the queries do not look like a walk or are too many to align (logged: they are matched as single
/// images).
fn walk_matches(detector: &Detector, queries: &[Vec<f32>], depth: usize) -> Result<Option<Vec<Vec<Match>>>> {
    let db = detector.db();
    if let Some(why) = walk::why_not_a_walk(queries) {
        log::info!("{why}, so they are matched as single images (detector.sequence.length 0)");
        return Ok(None);
    }
    if queries.len() * db.len() > walk::MAX_CELLS {
        log::info!(
            "{} queries against {} database images are too many to align as a walk (at most {} pairs), so they are matched as single images (detector.sequence.length 0)",
            queries.len(),
            db.len(),
            walk::MAX_CELLS
        );
        return Ok(None);
    }
    let scores: Vec<Vec<f32>> = queries
        .iter()
        .map(|q| {
            let prepared = db.prepare(q);
            (0..db.len()).map(|p| detector.descriptor().score(db.prepared_distance_to(&prepared, p).sqrt())).collect()
        })
        .collect();
    let (aligned, speed) = walk::align_walk(&scores, depth);
    log::info!("{} queries aligned as a walk moving {speed:.2} database images per query", queries.len());
    Ok(Some(
        aligned
            .into_iter()
            .zip(queries)
            .map(|(places, query)| {
                places
                    .into_iter()
                    .map(|(p, score)| Match {
                        id: db.id(p),
                        stamp: db.stamp(p),
                        distance: db.squared_distance_to(query, p).sqrt(),
                        score,
                    })
                    .collect()
            })
            .collect(),
    ))
}

/// Replays `source` (its `topics`, for a bag) through `pipeline`: keyframe selection applies,
/// keyframe ids are frame indexes. A source that breaks off ends the replay with what was read (see
/// [`ReplayRun::error`]).
pub fn run_source(pipeline: &mut Pipeline, source: &Path, topics: &Topics, progress: bool) -> Result<ReplayRun> {
    run_source_with(pipeline, source, topics, progress, |_, _| Ok(()))
}

/// As [`run_source`], calling `on_keyframe` with each keyframe and its candidates as soon as the
/// pipeline returns them (to write them out incrementally); an error from it ends the replay.
pub fn run_source_with(
    pipeline: &mut Pipeline,
    source: &Path,
    topics: &Topics,
    progress: bool,
    on_keyframe: impl FnMut(&ReplayedKeyframe, &[LoopCandidate]) -> Result<()> + Send,
) -> Result<ReplayRun> {
    // The whole replay on a rayon worker: see `runtime::on_worker`.
    crate::runtime::on_worker(|| replay_frames(pipeline, source, topics, progress, on_keyframe))
}

fn replay_frames(
    pipeline: &mut Pipeline,
    source: &Path,
    topics: &Topics,
    progress: bool,
    mut on_keyframe: impl FnMut(&ReplayedKeyframe, &[LoopCandidate]) -> Result<()>,
) -> Result<ReplayRun> {
    let resume_after = pipeline.store().and_then(|store| store.max_id());
    // The newest stored keyframe must be this source's frame of the same index and stamp: a
    // database is continued only with the source it was built from.
    let newest = match pipeline.store() {
        Some(store) => {
            store.last_keyframe()?.map(|(id, stamp, descriptor)| (id, stamp, descriptor, store.path().to_path_buf()))
        }
        None => None,
    };
    let frames = open_source_topics(source, topics)?;
    let mut tracker_poses = match &topics.poses {
        Some(path) => Some(TrackerPoses::read(path).context("reading the tracker poses (--poses)")?),
        None => None,
    };
    log::info!("replaying {}", frames.describe());
    adopt_carried_intrinsics(pipeline, frames.intrinsics())?;
    let bar = frames_bar(progress, frames.len_hint().unwrap_or(0));
    let started = Instant::now();
    let mut run = ReplayRun::default();
    for frame in frames {
        let frame = match frame {
            Ok(frame) => frame,
            Err(e) => {
                let Some(unreadable) = unreadable_frame(&e) else {
                    run.error = Some(format!("{e:#}"));
                    break;
                };
                // Its stamp keeps `frame_stamps` in step with the frame indexes.
                run.frames += 1;
                run.frame_stamps.push(unreadable.stamp);
                if let Some((id, stamp, _, db)) = newest.as_ref().filter(|newest| newest.0 == unreadable.index as u64) {
                    // The image cannot be compared, the stamp can.
                    ensure!(
                        unreadable.stamp == *stamp,
                        "keyframe database {} was built from another source: its keyframe {id} has stamp {stamp}, \
                         frame {id} of {} (unreadable) has stamp {}",
                        db.display(),
                        source.display(),
                        unreadable.stamp
                    );
                    log::warn!(
                        "{}: frame {id}, the keyframe database's newest keyframe, cannot be read now, so only its \
                         stamp shows that {} was built from this source: {}",
                        source.display(),
                        db.display(),
                        unreadable.reason
                    );
                }
                if resume_after.is_some_and(|last| unreadable.index as u64 <= last) {
                    run.skipped += 1;
                } else {
                    run.unreadable.skip(source, unreadable);
                }
                bar.inc(1);
                continue;
            }
        };
        run.frames += 1;
        run.frame_stamps.push(frame.stamp);
        if let Some((id, stamp, stored, db)) = &newest {
            if frame.index as u64 == *id {
                let another = |what: String| {
                    anyhow::anyhow!("keyframe database {} was built from another source: {what}", db.display())
                };
                if frame.stamp != *stamp {
                    return Err(another(format!(
                        "its keyframe {id} has stamp {stamp}, frame {id} of {} has stamp {}",
                        source.display(),
                        frame.stamp
                    )));
                }
                // Same stamp: the same image gives the same descriptor (up to float noise).
                let difference = crate::descriptor::distance(&pipeline.describe(&frame.image)?, stored);
                if difference.is_nan() || difference > 1e-3 {
                    return Err(another(format!(
                        "frame {id} of {} differs from its keyframe {id} (descriptor distance {difference:.3})",
                        source.display()
                    )));
                }
            }
        }
        if resume_after.is_some_and(|last| frame.index as u64 <= last) {
            run.skipped += 1;
            bar.inc(1);
            continue;
        }
        let tracker_pose = tracker_poses.as_mut().and_then(|poses| poses.at(frame.stamp));
        let outcome = pipeline
            .process_source_frame(&frame, tracker_pose)
            .with_context(|| format!("frame {} (stamp {}) of {}", frame.index, frame.stamp, source.display()))?;
        if outcome.keyframe.is_some() {
            let t = outcome.timings;
            run.total.network_ms += t.network_ms;
            run.total.descriptor_ms += t.descriptor_ms;
            run.total.detector_ms += t.detector_ms;
            run.total.verification_ms += t.verification_ms;
            run.rejected += outcome.rejected;
            run.rejected_by_odometry += outcome.rejected_by_odometry;
            run.unchecked_by_odometry += outcome.unchecked_by_odometry;
            let keyframe = ReplayedKeyframe {
                index: frame.index,
                stamp: frame.stamp,
                best: outcome.best,
                best_verified: outcome.best_verified,
            };
            on_keyframe(&keyframe, &outcome.candidates)?;
            run.keyframes.push(keyframe);
            run.candidates.extend(outcome.candidates);
            bar.set_message(format!("{} keyframes, {} candidates", run.keyframes.len(), run.candidates.len()));
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if run.frames == 0 && run.error.is_none() {
        bail!("{} holds no images to replay (an empty bag or an image topic without messages)", source.display());
    }
    if run.unreadable.count() > 0 && run.unreadable.count() == run.frames && run.error.is_none() {
        return Err(run.unreadable.none_readable(source, run.frames));
    }
    if let (Some((id, _, _, db)), None) = (&newest, &run.error) {
        anyhow::ensure!(
            run.frames as u64 > *id,
            "keyframe database {} was built from another source: it holds keyframe {id}, but {} has only {} frames",
            db.display(),
            source.display(),
            run.frames
        );
    }
    if let Some(poses) = &tracker_poses {
        // The frames that could be given a pose: read, and not by the earlier run.
        poses.report(run.frames - run.skipped - run.unreadable.count());
    }
    run.wall_secs = started.elapsed().as_secs_f64();
    Ok(run)
}
