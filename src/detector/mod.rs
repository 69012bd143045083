//! Keyframe database and loop-closure detector: which earlier keyframe, if any, does a new one revisit.
//!
//! [`KeyframeDb`] stores every keyframe's descriptor in one contiguous buffer, as `f32` or as six-level
//! codes of under a kilobyte ([`codes`], `detector.storage`), and answers top-k nearest-neighbour
//! queries: by an exact SIMD scan while small, and through an approximate inverted-file index it
//! builds by itself once large ([`index`]: when, how, and the recall it keeps).
//!
//! [`Detector`] applies the policy ([`DetectorParams`]) to each new keyframe: query the history, then
//! insert. Rules, in order:
//! 1. minimum history: no query while the database holds fewer than `min_history` keyframes (the paper's
//!    "number of historical feature vectors exceeds a certain threshold");
//! 2. recent exclusion: the last `exclude_recent_count` inserted keyframes and those less than
//!    `exclude_recent_secs` older than the query are never matched (with a non-zero time rule, keyframes
//!    stamped after the query are excluded too);
//! 3. the `top_k` nearest eligible keyframes whose distance passes the threshold are the query's matches;
//! 4. temporal consistency: with `consistency_queries = k > 1`, a match at database position `p` is
//!    reported only when each of the previous `k - 1` queries (consecutive calls of
//!    [`Detector::process`], including those that found nothing or ran before the minimum history) had a
//!    match that passed the threshold at a position within `consistency_window` keyframes of `p`.
//!    Positions (insertion order) rather than ids are compared so that any id scheme works.
//!    With `consistency_delayed` the check delays a loop rather than losing it: a held-back match of
//!    one of those `k - 1` queries is reported later, with its query's id and stamp, once a later query
//!    reports a match within `consistency_window` keyframes of it (each match once, at most `top_k` a
//!    query). So a revisit `k` or more keyframes long is reported from its first keyframe, not its
//!    `k`-th; only shorter ones are lost. Without it, held-back matches are dropped, as DBoW2 does.
//!
//! Reported candidates are ranked 0, 1, ... in increasing distance among those reported; with the
//! sequence policy on, in decreasing sequence score. (Geometric verification re-ranks those it keeps
//! by inliers: [`crate::verification::best_supported`].)
//!
//! Centring on the history: with `centre_on_history` (unit-vector descriptor modes; the paper's
//! descriptor is left as it is), a query and a keyframe are compared by the cosine of their
//! differences from the history's mean, `m = sum / (n + 1)` over the `n` keyframes searched (shrunk
//! towards zero while the history is short, so one keyframe does not cancel itself). Every image of
//! an environment shares a large common component (the same walls, light and camera); removing it
//! leaves what tells places apart. The score is `(1 + cos) / 2` of the centred vectors and the
//! distance `sqrt(2 - 2 cos)`, the `l2` mapping. The index finds the nearest
//! [`sequence::CANDIDATES`] by plain distance, which are re-ranked; the mean is a running sum, so
//! the stored descriptors never change.
//!
//! Sequence policy ([`sequence`]): with `sequence_length = L > 1`, a match's score is the mean
//! score along the diagonal of the last `L` queries against the history (a revisit is a run of
//! matches, not one), and the threshold applies to that score. It looks back only: a query's
//! answer comes with the query, no delay.
//!
//! Memory budget: with `max_keyframes = n > 0`, once the database holds more than `n` keyframes the
//! oldest are dropped from memory (and so from the search) until `n` remain; positions are renumbered
//! from the oldest kept keyframe and the consistency history follows. A persistent store ([`store`])
//! keeps every keyframe on disk regardless; a restart loads only the newest `n`.

pub mod codes;
mod huge_pages;
pub mod index;
pub mod rows;
pub mod selection;
pub mod sequence;
pub mod store;
pub mod walk;

use crate::descriptor::Descriptor;
use crate::types::{LoopCandidate, Stamp};
use anyhow::{ensure, Context};
use index::{IndexPolicy, IvfIndex, IvfTraining, TopK};
use rows::{DescriptorRows, PreparedQuery, Rows};
use std::borrow::Cow;
use std::collections::VecDeque;

pub use rows::RowFormat;

/// The acceptance threshold, on the distance or on the score (see [`crate::descriptor::Descriptor::score`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Threshold {
    /// A match is accepted when its descriptor distance is at most this.
    MaxDistance(f32),
    /// A match is accepted when its score is at least this.
    MinScore(f32),
}

/// The detector's policy.
#[derive(Clone, Debug, PartialEq)]
pub struct DetectorParams {
    pub threshold: Threshold,
    /// No query runs until the database holds at least this many keyframes.
    pub min_history: usize,
    /// The most recently inserted this-many keyframes are never matched.
    pub exclude_recent_count: usize,
    /// Keyframes less than this many seconds older than the query are never matched.
    pub exclude_recent_secs: f64,
    /// At most this many candidates per query (ranks 0..top_k).
    pub top_k: usize,
    /// A candidate is reported only when this many consecutive queries agree (1 disables the check).
    pub consistency_queries: usize,
    /// Matches agree when their database positions differ by at most this many keyframes.
    pub consistency_window: usize,
    /// Held-back matches are reported once later queries agree with them, not dropped (module doc).
    pub consistency_delayed: bool,
    /// At most this many keyframes are kept in memory and searched, the newest (0 = unlimited; module doc).
    pub max_keyframes: usize,
    /// Queries whose scores are accumulated along a diagonal (1 = single-image matching; module doc).
    pub sequence_length: usize,
    /// Compare descriptors after removing the history's mean (module doc).
    pub centre_on_history: bool,
    /// How the database keeps descriptors.
    pub storage: Storage,
}

impl DetectorParams {
    /// Why nothing can ever match under these values, where that is so: a memory budget that keeps
    /// no keyframe old enough for the recency rules, or fewer keyframes than the minimum history.
    pub fn never_matches(&self) -> Option<String> {
        let budget = self.max_keyframes;
        if budget == 0 {
            return None;
        }
        if budget <= self.exclude_recent_count {
            return Some(format!(
                "detector.max_keyframes ({budget}) keeps no keyframe beyond the detector.exclude_recent.count ({}) newest, which never match: nothing can match",
                self.exclude_recent_count
            ));
        }
        (budget < self.min_history).then(|| {
            format!(
                "detector.max_keyframes ({budget}) keeps fewer keyframes than detector.min_history ({}) asks for before matching: nothing can match",
                self.min_history
            )
        })
    }
}

/// How the keyframe database keeps descriptors (`detector.storage`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Storage {
    /// Six-level codes for the unit-vector modes whose `f32` rows would take over a kilobyte; `f32`
    /// for the rest, so the paper's descriptor (the reproduction) is kept exactly.
    #[default]
    Auto,
    F32,
    Levels6,
}

impl Storage {
    pub const NAMES: [&'static str; 3] = ["auto", "f32", "levels6"];

    pub fn name(self) -> &'static str {
        Self::NAMES[self as usize]
    }

    /// The row format for `descriptor`'s values.
    pub fn format_for(self, descriptor: &Descriptor) -> RowFormat {
        match self {
            Storage::F32 => RowFormat::F32,
            Storage::Levels6 => RowFormat::Levels6,
            Storage::Auto => {
                let unit = descriptor.mode != crate::descriptor::DescriptorMode::Paper;
                if unit && RowFormat::F32.row_bytes(descriptor.dim()) > 1024 {
                    RowFormat::Levels6
                } else {
                    RowFormat::F32
                }
            }
        }
    }
}

impl std::str::FromStr for Storage {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Storage::Auto),
            "f32" => Ok(Storage::F32),
            "levels6" => Ok(Storage::Levels6),
            _ => Err(format!("unknown storage {s:?} (expected one of {})", Self::NAMES.join(", "))),
        }
    }
}

/// One result of a database query: the keyframe's position (insertion order) and squared distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbour {
    pub position: usize,
    pub squared_distance: f32,
}

/// What the approximate index of a [`KeyframeDb`] looks like (for logs and benchmarks).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct IndexInfo {
    /// Inverted lists (k-means centroids).
    pub nlist: usize,
    /// Lists scanned per query.
    pub nprobe: usize,
    /// Keyframes the index was last trained on.
    pub trained_len: usize,
    /// Keyframes in the largest list (balance: the mean is `len / nlist`).
    pub largest_list: usize,
}

/// Keyframes (id, stamp, descriptor) in insertion order, with top-k search (exact, or indexed once large).
#[derive(Clone, Debug)]
pub struct KeyframeDb {
    dim: usize,
    ids: Vec<u64>,
    stamps: Vec<Stamp>,
    /// Keyframe after keyframe, in the database's [`RowFormat`].
    descriptors: Rows,
    /// Dropped keyframes still at the front of the vectors (removed in batches: see [`KeyframeDb::drop_oldest`]).
    dropped: usize,
    index_policy: IndexPolicy,
    index: Option<IvfIndex>,
    /// A retraining under way, advanced a slice per insert; `index` serves until it is done.
    training: Option<IvfTraining>,
    /// While set, inserts leave the index alone (bulk loading: one training at the end, not one per growth step).
    index_deferred: bool,
}

impl KeyframeDb {
    pub fn new(dim: usize) -> Self {
        Self::with_capacity(dim, 0)
    }

    /// An empty database of `f32` rows with room for `keyframes` keyframes (loading a stored history).
    pub fn with_capacity(dim: usize, keyframes: usize) -> Self {
        Self::with_format(RowFormat::F32, dim, keyframes)
    }

    /// An empty database keeping its rows in `format`, with room for `keyframes` keyframes.
    pub fn with_format(format: RowFormat, dim: usize, keyframes: usize) -> Self {
        KeyframeDb {
            dim,
            ids: Vec::with_capacity(keyframes),
            stamps: Vec::with_capacity(keyframes),
            descriptors: Rows::with_capacity(format, dim, keyframes),
            dropped: 0,
            index_policy: IndexPolicy::default(),
            index: None,
            training: None,
            index_deferred: false,
        }
    }

    /// A database holding a loaded history: `ids[i]`, `stamps[i]` and the `i`th `dim` values of
    /// `descriptors` are one keyframe, in insertion order; every descriptor must have passed
    /// [`KeyframeDb::check_descriptor`]. The index is deferred to the next insert, as after
    /// [`KeyframeDb::index_at_next_insert`].
    pub(crate) fn from_history(
        dim: usize,
        ids: Vec<u64>,
        stamps: Vec<Stamp>,
        descriptors: DescriptorRows,
    ) -> anyhow::Result<Self> {
        ensure!(
            ids.len() == stamps.len() && ids.len() * dim == descriptors.len(),
            "a history of {} ids, {} stamps and {} values of {dim}-value descriptors does not add up",
            ids.len(),
            stamps.len(),
            descriptors.len()
        );
        Ok(KeyframeDb { ids, stamps, descriptors: Rows::plain(dim, descriptors), ..Self::new(dim) })
    }

    /// How the rows are kept.
    pub fn format(&self) -> RowFormat {
        self.descriptors.format()
    }

    /// This database with its rows in `format` (coding is lossy); the index is rebuilt at the next
    /// insert, as after a load.
    pub fn into_format(mut self, format: RowFormat) -> Self {
        if self.format() != format {
            self.descriptors = self.descriptors.into_format(format);
            self.index = None;
            self.training = None;
        }
        self
    }

    /// Changes when the approximate index is used; builds or drops it at once to match.
    pub fn set_index_policy(&mut self, policy: IndexPolicy) -> anyhow::Result<()> {
        self.index_policy = policy;
        // A retraining under way restarts under the new policy if it is still due.
        self.training = None;
        if self.len() < policy.threshold(self.dim) {
            self.index = None;
        }
        self.update_index()
    }

    /// Defers index maintenance while `deferred` (a bulk load); clearing it builds or extends the index
    /// for everything inserted meanwhile. Searches stay correct in between (unindexed keyframes are scanned).
    pub fn defer_index(&mut self, deferred: bool) -> anyhow::Result<()> {
        self.index_deferred = deferred;
        self.update_index()
    }

    /// Ends a deferral without building now: the next insert (or [`KeyframeDb::defer_index`]) builds or
    /// extends the index. A store load ends this way so that loading stays fast (100k 1280-d keyframes:
    /// well under a second, where the index build takes 2.7 s); searches in between scan exactly.
    pub fn index_at_next_insert(&mut self) {
        self.index_deferred = false;
    }

    pub fn index_policy(&self) -> IndexPolicy {
        self.index_policy
    }

    /// The approximate index's shape, or `None` while searches are exact.
    pub fn index_info(&self) -> Option<IndexInfo> {
        self.index.as_ref().map(|i| IndexInfo {
            nlist: i.nlist(),
            nprobe: i.nprobe(),
            trained_len: i.trained_len(),
            largest_list: i.largest_list(),
        })
    }

    /// Trains, retrains or extends the index as the policy and the database length require.
    fn update_index(&mut self) -> anyhow::Result<()> {
        if self.index_deferred {
            return Ok(());
        }
        if let Some(training) = &mut self.training {
            if let Some(index) = training
                .step(&self.descriptors, self.index_policy.retrain_slice_macs)
                .context("retraining the search index")?
            {
                self.index = Some(index);
                self.training = None;
            }
        }
        let len = self.len();
        let (policy, dim, first_live) = (self.index_policy, self.dim, self.dropped);
        match &mut self.index {
            // The first index is built at once: until it exists every query is an exact scan.
            None if len >= policy.threshold(dim) => {
                self.index = Some(
                    IvfIndex::train(&self.descriptors, first_live, policy.probe_fraction)
                        .context("training the search index")?,
                )
            }
            None => {}
            Some(index) => {
                if self.training.is_none() && len >= index.trained_len().saturating_mul(policy.retrain_growth.max(2)) {
                    self.training = Some(IvfTraining::start(&self.descriptors, first_live, policy.probe_fraction));
                }
                if index.pending(&self.descriptors) >= index::ASSIGN_BATCH {
                    index
                        .assign_pending(&self.descriptors, self.descriptors.slots())
                        .context("extending the search index")?;
                }
            }
        }
        Ok(())
    }

    /// Drops the `count` oldest keyframes (all, if fewer); later positions shift down by `count`.
    /// The memory is reclaimed once the dropped ones reach an eighth of those kept, so dropping one
    /// keyframe per insertion costs amortised O(dim), with at most 1/8 extra memory.
    pub fn drop_oldest(&mut self, count: usize) {
        self.dropped += count.min(self.len());
        if self.dropped > 0 && self.dropped >= self.len() / 8 {
            self.ids.drain(..self.dropped);
            self.stamps.drain(..self.dropped);
            self.descriptors.drain_front(self.dropped);
            if let Some(index) = &mut self.index {
                index.drain(self.dropped);
            }
            if let Some(training) = &mut self.training {
                training.drain(self.dropped);
            }
            self.dropped = 0;
        }
    }

    fn stamps(&self) -> &[Stamp] {
        &self.stamps[self.dropped..]
    }

    /// Whether the descriptors are a map of a keyframe store's vector file ([`rows`]).
    pub fn is_mapped(&self) -> bool {
        self.descriptors.is_mapped()
    }

    /// Descriptor length every keyframe must have.
    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn len(&self) -> usize {
        self.ids.len() - self.dropped
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Ok when `descriptor` has `dim` values, all finite; otherwise an error naming `what` and the fault.
    pub(crate) fn check_descriptor(dim: usize, descriptor: &[f32], what: impl std::fmt::Display) -> anyhow::Result<()> {
        ensure!(
            descriptor.len() == dim,
            "{what} descriptor has {} values, the database holds {dim}-value descriptors",
            descriptor.len(),
        );
        // A branch-free pass (it vectorises); the position is looked for only on failure.
        if !descriptor.iter().fold(true, |ok, x| ok & x.is_finite()) {
            let i = descriptor.iter().position(|x| !x.is_finite()).unwrap_or(0);
            anyhow::bail!("{what} descriptor value {i} is {} (not finite)", descriptor[i]);
        }
        Ok(())
    }

    /// Appends a keyframe; returns its position. Refuses a descriptor of the wrong length or with a
    /// non-finite value (it would poison every later distance).
    pub fn insert(&mut self, id: u64, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<usize> {
        Self::check_descriptor(self.dim, descriptor, format_args!("keyframe {id}"))?;
        self.ids.push(id);
        self.stamps.push(stamp);
        self.descriptors.extend(descriptor);
        self.update_index()?;
        Ok(self.len() - 1)
    }

    /// Id of the keyframe at `position` (panics out of range, like slice indexing; positions come from
    /// [`KeyframeDb::insert`] or [`KeyframeDb::nearest`]).
    pub fn id(&self, position: usize) -> u64 {
        self.ids[self.dropped + position]
    }

    pub fn stamp(&self, position: usize) -> Stamp {
        self.stamps()[position]
    }

    /// The stored descriptor at `position`: as inserted with `f32` rows, its reconstruction with codes.
    pub fn descriptor(&self, position: usize) -> Cow<'_, [f32]> {
        let slot = self.dropped + position;
        self.descriptors.values(slot, slot + 1)
    }

    /// Squared distance from `query` to the keyframe at `position`, as the search computes it (exact
    /// for `f32` rows, the estimate for codes: [`codes`]).
    pub fn squared_distance_to(&self, query: &[f32], position: usize) -> f32 {
        self.prepared_distance_to(&self.descriptors.prepare(query), position)
    }

    /// [`KeyframeDb::squared_distance_to`] for a query prepared once ([`KeyframeDb::prepare`]) and
    /// compared with many keyframes.
    pub(crate) fn prepared_distance_to(&self, query: &PreparedQuery, position: usize) -> f32 {
        let mut found = 0.0;
        let slot = self.dropped + position;
        self.descriptors.scan(query, std::iter::once((position, slot)), |_, d2| found = d2);
        found
    }

    /// A query prepared for the rows' format (for codes: rounded once, see [`codes`]).
    pub(crate) fn prepare<'q>(&self, query: &'q [f32]) -> PreparedQuery<'q> {
        self.descriptors.prepare(query)
    }

    /// The `k` keyframes nearest to `query` among the positions `eligible` accepts, nearest first (equal
    /// distances: earlier position first). Exact while the database is below the index threshold,
    /// approximate above it ([`index`]). Allocates only the result.
    pub fn nearest(
        &self,
        query: &[f32],
        k: usize,
        eligible: impl Fn(usize) -> bool + Sync,
    ) -> anyhow::Result<Vec<Neighbour>> {
        Self::check_descriptor(self.dim, query, "query")?;
        let prepared = self.descriptors.prepare(query);
        if let Some(index) = self.index.as_ref().filter(|_| k > 0) {
            if let Some(found) = index.nearest(&self.descriptors, self.dropped, query, &prepared, k, &eligible) {
                return Ok(found);
            }
        }
        Ok(self.scan_exact(&prepared, k, eligible))
    }

    /// [`KeyframeDb::nearest`] by the exact scan, whatever the size (the reference for the index's recall).
    pub fn nearest_exact(
        &self,
        query: &[f32],
        k: usize,
        eligible: impl Fn(usize) -> bool,
    ) -> anyhow::Result<Vec<Neighbour>> {
        Self::check_descriptor(self.dim, query, "query")?;
        Ok(self.scan_exact(&self.descriptors.prepare(query), k, eligible))
    }

    fn scan_exact(&self, query: &PreparedQuery<'_>, k: usize, eligible: impl Fn(usize) -> bool) -> Vec<Neighbour> {
        if k == 0 || self.dim == 0 {
            // A zero-length descriptor makes every keyframe equally near; take the first eligible ones.
            return (0..self.len())
                .filter(|&p| eligible(p))
                .take(k)
                .map(|position| Neighbour { position, squared_distance: 0.0 })
                .collect();
        }
        let mut top = TopK::new(k);
        let live = (0..self.len()).filter(|&p| eligible(p)).map(|p| (p, p + self.dropped));
        self.descriptors.scan(query, live, |position, d2| top.offer(position, d2));
        top.into_vec()
    }
}

/// The best eligible match of a query, threshold and consistency aside (see [`Detector::best_match`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    pub id: u64,
    pub stamp: Stamp,
    pub distance: f32,
    pub score: f32,
}

/// A recent query as temporal consistency remembers it.
#[derive(Clone, Debug)]
struct RecentQuery {
    id: u64,
    stamp: Stamp,
    /// Its threshold-passing matches, best first, as (position, distance, score) and whether
    /// consistency held the match back: the `top_k` best, which later queries must agree with, then
    /// the alternatives verification checks (`process_ranked`'s `depth`).
    matches: Vec<((usize, f32, f32), bool)>,
    /// Candidates reported for it so far (what verification kept, where [`Detector::set_reported`] says).
    reported: usize,
}

/// What temporal consistency remembers of the last queries ([`Detector::consistency_state`]), by
/// keyframe id rather than database position, so that a store can keep it with each keyframe and a
/// restart go on where the stopped run left off ([`Detector::resume`]).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ConsistencyState {
    /// Oldest first.
    pub queries: Vec<RecentQueryState>,
}

/// One recent query of a [`ConsistencyState`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RecentQueryState {
    pub id: u64,
    pub stamp: Stamp,
    /// Its threshold-passing matches, best first: (match id, distance, score, held back).
    pub matches: Vec<(u64, f32, f32, bool)>,
    /// Candidates reported for it so far.
    pub reported: usize,
}

/// The loop-closure detector: a keyframe database plus the policy of the module doc.
#[derive(Clone, Debug)]
pub struct Detector {
    descriptor: Descriptor,
    params: DetectorParams,
    db: KeyframeDb,
    /// The last `consistency_queries` queries' threshold-passing matches, oldest first: the newest is
    /// the latest query's, the others those it had to agree with.
    recent_matches: VecDeque<RecentQuery>,
    /// Descriptors of the last `sequence_length - 1` queries, oldest first (the sequence policy).
    recent_queries: sequence::RecentQueries,
    /// Sum of the searched keyframes' descriptors (centring on the history).
    history_sum: Vec<f64>,
}

impl Detector {
    /// An empty detector for descriptors of `descriptor`'s mode (whose score defines the threshold).
    pub fn new(descriptor: Descriptor, params: DetectorParams) -> Self {
        if let Some(why) = params.never_matches() {
            log::warn!("{why}");
        }
        let recent_queries = sequence::RecentQueries::new(params.sequence_length);
        let history_sum = vec![0.0; descriptor.dim()];
        Detector {
            db: KeyframeDb::with_format(params.storage.format_for(&descriptor), descriptor.dim(), 0),
            descriptor,
            params,
            recent_matches: VecDeque::new(),
            recent_queries,
            history_sum,
        }
    }

    pub fn params(&self) -> &DetectorParams {
        &self.params
    }

    /// Changes the policy at run time (a node's `set_parameters`); the database is kept (in the new
    /// storage format, if that changed), and the consistency history is trimmed to the new length.
    pub fn set_params(&mut self, params: DetectorParams) {
        if let Some(why) = params.never_matches().filter(|_| params.never_matches() != self.params.never_matches()) {
            log::warn!("{why}");
        }
        self.params = params;
        let format = self.params.storage.format_for(&self.descriptor);
        if format != self.db.format() {
            let db = std::mem::replace(&mut self.db, KeyframeDb::new(0));
            self.db = db.into_format(format);
            self.resum_history();
        }
        self.trim_recent_matches();
        self.recent_queries.set_length(self.params.sequence_length);
        self.enforce_budget();
    }

    /// Replaces the history with `db` (a stored history being loaded); the consistency history restarts.
    /// The memory budget applies. A history large enough for the search index gets it now (seconds at
    /// 100k 1280-d keyframes), at start-up, rather than holding up the first keyframe.
    pub fn replace_history(&mut self, db: KeyframeDb) -> anyhow::Result<()> {
        ensure!(
            db.dim() == self.db.dim(),
            "the history has {}-value descriptors, the detector's descriptor {}",
            db.dim(),
            self.db.dim()
        );
        self.db = db.into_format(self.params.storage.format_for(&self.descriptor));
        self.recent_matches.clear();
        self.recent_queries.clear();
        self.resum_history();
        self.enforce_budget();
        self.db.defer_index(false).context("indexing the loaded history")
    }

    /// What temporal consistency remembers after the latest query, for a store to keep beside that
    /// keyframe; `None` with consistency off.
    pub fn consistency_state(&self) -> Option<ConsistencyState> {
        (self.params.consistency_queries > 1).then(|| ConsistencyState {
            queries: self
                .recent_matches
                .iter()
                .map(|recent| RecentQueryState {
                    id: recent.id,
                    stamp: recent.stamp,
                    matches: recent.matches.iter().map(|&((p, d, s), held)| (self.db.id(p), d, s, held)).collect(),
                    reported: recent.reported,
                })
                .collect(),
        })
    }

    /// After [`Detector::replace_history`] with a stored history, goes on as the run that stored it
    /// would have: `recent` are the descriptors of its newest keyframes, oldest first (the earlier
    /// queries of the sequence policy), and `consistency` what temporal consistency remembered after
    /// the newest ([`Detector::consistency_state`]), which applies only with consistency on. Matches
    /// of keyframes no longer in the history (the memory budget) are dropped.
    pub fn resume(&mut self, recent: &[Vec<f32>], consistency: Option<ConsistencyState>) {
        // They are the history's newest keyframes: the one at position `q` was matched against the
        // `q` before it.
        let first = self.db.len().saturating_sub(recent.len());
        for (position, descriptor) in (first..).zip(recent) {
            let stamp = self.db.stamps().get(position).copied().unwrap_or(Stamp::from_nanos(0));
            self.recent_queries.push(descriptor, stamp, position);
        }
        let Some(state) = consistency.filter(|_| self.params.consistency_queries > 1) else { return };
        let wanted: std::collections::HashSet<u64> =
            state.queries.iter().flat_map(|q| q.matches.iter().map(|m| m.0)).collect();
        let positions: std::collections::HashMap<u64, usize> =
            (0..self.db.len()).map(|p| (self.db.id(p), p)).filter(|(id, _)| wanted.contains(id)).collect();
        self.recent_matches = state
            .queries
            .into_iter()
            .map(|query| RecentQuery {
                id: query.id,
                stamp: query.stamp,
                matches: query
                    .matches
                    .iter()
                    .filter_map(|&(id, d, s, held)| Some(((*positions.get(&id)?, d, s), held)))
                    .collect(),
                reported: query.reported,
            })
            .collect();
        self.trim_recent_matches();
    }

    /// Keeps the consistency history to the queries the policy needs (module doc).
    fn trim_recent_matches(&mut self) {
        let keep = self.params.consistency_queries.max(1);
        while self.recent_matches.len() > keep {
            self.recent_matches.pop_front();
        }
    }

    /// Recomputes the history's sum from the stored descriptors.
    fn resum_history(&mut self) {
        self.history_sum.iter_mut().for_each(|s| *s = 0.0);
        for position in 0..self.db.len() {
            add_into(&mut self.history_sum, &self.db.descriptor(position), 1.0);
        }
    }

    /// Inserts into the database and adds the descriptor as stored (a code's reconstruction) to the
    /// history's sum, as dropping it will subtract it.
    fn store(&mut self, id: u64, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<()> {
        let position = self.db.insert(id, stamp, descriptor)?;
        add_into(&mut self.history_sum, &self.db.descriptor(position), 1.0);
        Ok(())
    }

    /// Drops the oldest keyframes beyond `max_keyframes` (module doc); consistency positions follow.
    fn enforce_budget(&mut self) {
        let max = self.params.max_keyframes;
        if max == 0 || self.db.len() <= max {
            return;
        }
        let excess = self.db.len() - max;
        for position in 0..excess {
            add_into(&mut self.history_sum, &self.db.descriptor(position), -1.0);
        }
        self.db.drop_oldest(excess);
        self.recent_queries.history_dropped(excess);
        for recent in &mut self.recent_matches {
            recent.matches.retain(|&((p, ..), _)| p >= excess);
            recent.matches.iter_mut().for_each(|((p, ..), _)| *p -= excess);
        }
    }

    pub fn descriptor(&self) -> &Descriptor {
        &self.descriptor
    }

    pub fn db(&self) -> &KeyframeDb {
        &self.db
    }

    /// Bytes of memory one keyframe's descriptor takes in the database.
    pub fn row_bytes(&self) -> usize {
        self.db.format().row_bytes(self.db.dim())
    }

    /// The threshold as a distance: matches at most this far apart pass.
    pub fn max_distance(&self) -> f32 {
        match self.params.threshold {
            Threshold::MaxDistance(d) => d,
            Threshold::MinScore(s) => self.descriptor.distance_for_score(s),
        }
    }

    /// The threshold as a score: matches scoring at least this pass.
    pub fn min_score(&self) -> f32 {
        match self.params.threshold {
            Threshold::MaxDistance(d) => self.descriptor.score(d),
            Threshold::MinScore(s) => s,
        }
    }

    /// Whether a ranked match passes the threshold. Where the sequence or centring policy sets the
    /// score, the threshold applies to that score (a distance threshold as its score), not to the
    /// query's own distance.
    fn passes(&self, distance: f32, score: f32) -> bool {
        let policy_scored = self.params.sequence_length > 1 || self.centring_applies();
        match self.params.threshold {
            Threshold::MaxDistance(d) if !policy_scored => distance <= d,
            Threshold::MaxDistance(_) => score >= self.min_score(),
            Threshold::MinScore(s) => score >= s,
        }
    }

    /// The `k` nearest keyframes the history and recency rules allow for a query at `stamp`; empty
    /// before the minimum history.
    fn eligible_nearest(&self, stamp: Stamp, descriptor: &[f32], k: usize) -> anyhow::Result<Vec<Neighbour>> {
        if self.db.len() < self.params.min_history.max(1) {
            // Still validate the query so bad input is reported at once, not only later.
            KeyframeDb::check_descriptor(self.db.dim, descriptor, "query")?;
            return Ok(Vec::new());
        }
        self.db.nearest(descriptor, k, self.eligibility(stamp))
    }

    /// Whether the keyframe at a position may match a query at `stamp` (the recency rules); the
    /// rule's values are worked out once, as the scan calls it for every keyframe.
    fn eligibility(&self, stamp: Stamp) -> impl Fn(usize) -> bool + '_ {
        self.eligibility_against(stamp, self.db.len())
    }

    /// [`Detector::eligibility`] for a query that came when the history held `history_len`
    /// keyframes (an earlier query of a sequence window).
    fn eligibility_against(&self, stamp: Stamp, history_len: usize) -> impl Fn(usize) -> bool + '_ {
        let last_eligible = history_len.saturating_sub(self.params.exclude_recent_count);
        let min_age_nanos = (self.params.exclude_recent_secs * 1e9).round() as i64;
        let time_rule = self.params.exclude_recent_secs > 0.0;
        let stamps = self.db.stamps();
        move |p| p < last_eligible && (!time_rule || stamp.nanos.saturating_sub(stamps[p].nanos) >= min_age_nanos)
    }

    /// The eligible matches of a query, best first: the `top_k` nearest, or with the sequence policy the
    /// nearest [`sequence::CANDIDATES`] re-ranked by sequence score. Each is (position, distance, score).
    /// `ahead` are the queries after this one that join its sequence window (database/query mode).
    fn ranked_matches(
        &self,
        stamp: Stamp,
        descriptor: &[f32],
        ahead: &[Vec<f32>],
        top_k: usize,
    ) -> anyhow::Result<Vec<(usize, f32, f32)>> {
        let centring = self.centring();
        if self.params.sequence_length <= 1 && centring.is_none() {
            let neighbours = self.eligible_nearest(stamp, descriptor, top_k)?;
            return Ok(neighbours
                .iter()
                .map(|n| {
                    let distance = n.squared_distance.sqrt();
                    (n.position, distance, self.descriptor.score(distance))
                })
                .collect());
        }
        let neighbours = self.eligible_nearest(stamp, descriptor, top_k.max(sequence::CANDIDATES))?;
        // Each query of the window by its own recency rules: the current one's for it and for the
        // later ones (which are not in the history), and an earlier one's as they were when it came.
        let eligible_now = self.eligibility(stamp);
        let earlier: Vec<Box<dyn Fn(usize) -> bool + '_>> = (1..self.params.sequence_length)
            .map_while(|age| self.recent_queries.judged_by(age))
            .map(|(stamp, len)| Box::new(self.eligibility_against(stamp, len)) as Box<dyn Fn(usize) -> bool>)
            .collect();
        let eligible = |offset: isize, p: usize| match offset {
            0.. => eligible_now(p),
            _ => earlier.get(offset.unsigned_abs() - 1).is_some_and(|rule| rule(p)),
        };
        // The window's queries: the current one, the kept earlier ones (by age), then the later ones;
        // each prepared once for the rows.
        let ahead = &ahead[..ahead.len().min(self.params.sequence_length.saturating_sub(1))];
        let behind = self.recent_queries.behind(ahead.len());
        let queries: Vec<&[f32]> = std::iter::once(descriptor)
            .chain(self.recent_queries.newest_first().take(behind))
            .chain(ahead.iter().map(Vec::as_slice))
            .collect();
        let index = |offset: isize| if offset <= 0 { offset.unsigned_abs() } else { behind + offset as usize };
        let prepared: Vec<PreparedQuery> = match centring {
            Some(_) => Vec::new(),
            None => queries.iter().map(|q| self.db.prepare(q)).collect(),
        };
        // (distance, score) of the query `offset` steps from the current one against keyframe `p`,
        // centred or not.
        let compare = |offset: isize, p: usize| -> (f32, f32) {
            let q = index(offset);
            match &centring {
                Some(mean) => centred_comparison(queries[q], &self.db.descriptor(p), mean),
                None => {
                    let distance = self.db.prepared_distance_to(&prepared[q], p).sqrt();
                    (distance, self.descriptor.score(distance))
                }
            }
        };
        let mut ranked: Vec<(usize, f32, f32)> = neighbours
            .iter()
            .map(|n| {
                let (distance, single) = compare(0, n.position);
                let score = if self.params.sequence_length > 1 {
                    self.recent_queries.sequence_score(
                        ahead.len(),
                        n.position,
                        self.db.len(),
                        |offset, p| compare(offset, p).1,
                        eligible,
                    )
                } else {
                    single
                };
                (n.position, distance, score)
            })
            .collect();
        // Stable: equal scores keep the nearer (by plain distance) first.
        ranked.sort_by(|a, b| b.2.total_cmp(&a.2));
        ranked.truncate(top_k);
        Ok(ranked)
    }

    /// Whether centring applies ([`Detector::centring`]).
    fn centring_applies(&self) -> bool {
        let unit_vectors = self.descriptor.mode != crate::descriptor::DescriptorMode::Paper;
        self.params.centre_on_history && unit_vectors && !self.db.is_empty()
    }

    /// The mean the history's descriptors are centred on, when centring applies (module doc).
    fn centring(&self) -> Option<Vec<f32>> {
        self.centring_applies().then(|| {
            let shrunk = (self.db.len() + 1) as f64;
            self.history_sum.iter().map(|s| (s / shrunk) as f32).collect()
        })
    }

    /// Queries the history with a new keyframe, then inserts it; returns the loop candidates reported
    /// under the full policy (module doc): earlier queries' that it confirmed first (their own
    /// `query_id`), then its own.
    pub fn process(&mut self, id: u64, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<Vec<LoopCandidate>> {
        let own = self.process_ranked(id, stamp, descriptor, self.params.top_k)?.1;
        let mut candidates = self.confirm_held_back(id, &own, self.params.top_k);
        candidates.extend(own);
        Ok(candidates)
    }

    /// [`Detector::process`] that also returns the `depth` nearest eligible keyframes, best first, whether
    /// or not they pass (the first is what [`Detector::best_match`] gives), from the same search: one search
    /// per keyframe, not two. With `depth` above `top_k`, up to `depth` candidates are returned: the
    /// alternatives geometric verification checks beside the best (`verification.candidates`);
    /// consistency still remembers only the `top_k` best. The candidates
    /// are the query's own; [`Detector::confirm_held_back`] then gives those of earlier queries
    /// that the reported ones confirm.
    pub fn process_ranked(
        &mut self,
        id: u64,
        stamp: Stamp,
        descriptor: &[f32],
        depth: usize,
    ) -> anyhow::Result<(Vec<Match>, Vec<LoopCandidate>)> {
        let ranked = self.ranked_matches(stamp, descriptor, &[], depth.max(self.params.top_k))?;
        let nearest = ranked.iter().map(|&m| self.to_match(m)).collect();
        let passing: Vec<(usize, f32, f32)> =
            ranked.into_iter().filter(|&(_, distance, score)| self.passes(distance, score)).collect();
        let needed = self.params.consistency_queries.saturating_sub(1);
        let (window, top_k) = (self.params.consistency_window, self.params.top_k);
        let consistent = |position: usize| {
            self.recent_matches.len() >= needed
                && self.recent_matches.iter().rev().take(needed).all(|earlier| {
                    earlier.matches.iter().take(top_k).any(|&((q, ..), _)| q.abs_diff(position) <= window)
                })
        };
        let matches: Vec<((usize, f32, f32), bool)> = passing.iter().map(|&m| (m, !consistent(m.0))).collect();
        let own: Vec<(usize, f32, f32)> = matches.iter().filter(|(_, held)| !held).map(|&(m, _)| m).collect();
        let candidates: Vec<LoopCandidate> =
            own.iter().enumerate().map(|(rank, &m)| self.candidate(id, stamp, m, rank)).collect();
        let history_len = self.db.len();
        self.store(id, stamp, descriptor)?;
        self.recent_queries.push(descriptor, stamp, history_len);
        if needed > 0 {
            let reported = own.len().min(top_k);
            self.recent_matches.push_back(RecentQuery { id, stamp, matches, reported });
            // The `needed` before the next query, and this one's own for `confirm_held_back`.
            while self.recent_matches.len() > needed + 1 {
                self.recent_matches.pop_front();
            }
        }
        self.enforce_budget();
        Ok((nearest, candidates))
    }

    /// The nearest keyframe the history and recency rules allow, ignoring the threshold, `top_k` and
    /// consistency (for precision-recall sweeps); `None` before the minimum history or when no keyframe is
    /// eligible. Does not insert: call [`Detector::insert`] afterwards.
    /// With the sequence policy the score is the sequence score over this query and the earlier ones
    /// that went through [`Detector::process`] or [`Detector::query`].
    pub fn best_match(&self, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<Option<Match>> {
        Ok(self.ranked_matches(stamp, descriptor, &[], 1)?.first().map(|&m| self.to_match(m)))
    }

    /// [`Detector::best_match`] for a query that is not inserted (database/query evaluation), which
    /// joins the sequence of recent queries.
    pub fn query(&mut self, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<Option<Match>> {
        Ok(self.query_ranked(stamp, descriptor, &[], 1)?.into_iter().next())
    }

    /// [`Detector::query`] with the `depth` nearest eligible keyframes, best first. With the sequence
    /// policy, `ahead` are the queries after this one (nearest first) that join its window, where
    /// they are known beforehand ([`sequence::queries_ahead`]); up to `length - 1` are used.
    pub fn query_ranked(
        &mut self,
        stamp: Stamp,
        descriptor: &[f32],
        ahead: &[Vec<f32>],
        depth: usize,
    ) -> anyhow::Result<Vec<Match>> {
        let ranked = self.ranked_matches(stamp, descriptor, ahead, depth)?;
        self.recent_queries.push(descriptor, stamp, self.db.len());
        Ok(ranked.into_iter().map(|m| self.to_match(m)).collect())
    }

    /// The candidate of query `id` for the match at `position`.
    fn candidate(
        &self,
        id: u64,
        stamp: Stamp,
        (position, distance, score): (usize, f32, f32),
        rank: usize,
    ) -> LoopCandidate {
        LoopCandidate {
            query_id: id,
            query_stamp: stamp,
            match_id: self.db.id(position),
            match_stamp: self.db.stamp(position),
            distance,
            score,
            rank: rank as u32,
            verified: None,
        }
    }

    /// After [`Detector::process_ranked`] for query `id`, given the candidates finally `reported` for it
    /// (what geometric verification kept of those the detector gave, or all of them): the matches of
    /// the queries before it that consistency held back and that lie within `consistency_window`
    /// keyframes of a reported one, oldest query first, each query's best first. Those queries
    /// agreed with the reported match, so together they make the run of agreeing queries the
    /// policy asks for (module doc). Each match is released once, and a query gets at most `depth`
    /// candidates in all (alternatives for verification to try in turn), ranked after those it
    /// already reported; say what verification kept of them with [`Detector::set_reported`].
    pub fn confirm_held_back(&mut self, id: u64, reported: &[LoopCandidate], depth: usize) -> Vec<LoopCandidate> {
        if !self.params.consistency_delayed {
            return Vec::new();
        }
        let window = self.params.consistency_window;
        let Some(current) = self.recent_matches.back_mut().filter(|r| r.id == id) else { return Vec::new() };
        current.reported = reported.len();
        let db = &self.db;
        let positions: Vec<usize> = current
            .matches
            .iter()
            .map(|&((position, ..), _)| position)
            .filter(|&position| reported.iter().any(|c| c.match_id == db.id(position)))
            .collect();
        let mut confirmed = Vec::new();
        let earlier = self.recent_matches.len() - 1;
        for index in 0..earlier {
            let recent = &self.recent_matches[index];
            let agrees = |position: usize| positions.iter().any(|&p| position.abs_diff(p) <= window);
            let released: Vec<usize> = (0..recent.matches.len())
                .filter(|&i| recent.matches[i].1 && agrees(recent.matches[i].0 .0))
                .take(depth.saturating_sub(recent.reported))
                .collect();
            for (rank, &i) in released.iter().enumerate() {
                confirmed.push(self.candidate(recent.id, recent.stamp, recent.matches[i].0, recent.reported + rank));
            }
            released.iter().for_each(|&i| self.recent_matches[index].matches[i].1 = false);
        }
        confirmed
    }

    /// Tells temporal consistency how many candidates were finally reported for the recent query `id`
    /// (what geometric verification kept of those [`Detector::confirm_held_back`] released), so that
    /// its matches confirmed later fill only the places left.
    pub fn set_reported(&mut self, id: u64, reported: usize) {
        if let Some(recent) = self.recent_matches.iter_mut().find(|r| r.id == id) {
            recent.reported = reported;
        }
    }

    fn to_match(&self, (position, distance, score): (usize, f32, f32)) -> Match {
        Match { id: self.db.id(position), stamp: self.db.stamp(position), distance, score }
    }

    /// Inserts a keyframe without querying (pairs with [`Detector::best_match`]).
    pub fn insert(&mut self, id: u64, stamp: Stamp, descriptor: &[f32]) -> anyhow::Result<()> {
        self.store(id, stamp, descriptor)?;
        self.enforce_budget();
        Ok(())
    }
}

/// `sum += sign * values`.
fn add_into(sum: &mut [f64], values: &[f32], sign: f64) {
    sum.iter_mut().zip(values).for_each(|(s, &v)| *s += sign * v as f64);
}

/// (distance, score) of `a` against `b` after subtracting `mean` from both: the cosine of the
/// differences, as `l2` maps it (module doc). A difference of zero length compares as orthogonal.
fn centred_comparison(a: &[f32], b: &[f32], mean: &[f32]) -> (f32, f32) {
    let (mut dot, mut aa, mut bb) = (0.0f32, 0.0f32, 0.0f32);
    for ((&x, &y), &m) in a.iter().zip(b).zip(mean) {
        let (x, y) = (x - m, y - m);
        dot += x * y;
        aa += x * x;
        bb += y * y;
    }
    let cos = if aa > 0.0 && bb > 0.0 { (dot / (aa.sqrt() * bb.sqrt())).clamp(-1.0, 1.0) } else { 0.0 };
    ((2.0 - 2.0 * cos).max(0.0).sqrt(), (1.0 + cos) / 2.0)
}

#[cfg(test)]
mod tests;
