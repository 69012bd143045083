//! A keyframe database on disk that survives crashes: every accepted keyframe (id, stamp, descriptor) is
//! committed together with its loop candidates before they leave the process, and a restarted replay
//! or node loads the stored keyframes back as the detector's history (and a replay rewrites its CSV
//! from the stored candidates, so a line a kill kept from the file comes back).
//!
//! Storage: one SQLite file (rusqlite, bundled), chosen over a hand-written append-only log because
//! SQLite already gives what the log would have to re-invent and test: atomic commits (a kill -9 at any
//! moment leaves either the whole keyframe or nothing, never a file that fails to open), a checked
//! format, unique ids enforced by an index, and plain SQL for `db info` / `export` / `merge`. It is
//! already a dependency (ROS 2 bags).
//! - WAL journal, `synchronous=FULL`, one transaction per keyframe (its row, and its candidates as
//!   JSON in `candidates` when it has any; meta `candidates` is `all` when every keyframe's are there): in WAL mode `NORMAL`
//!   survives a process crash but may lose the last commits on power loss or an OS crash, while `FULL`
//!   fsyncs the WAL on every commit. Keyframes come at a few per second and each costs tens of
//!   milliseconds of network time, so one fsync per keyframe (about a millisecond, see the tests) is
//!   cheap, and "stored before published" then holds for power loss too.
//! - `page_size=16384`: a 1280-value `f32` descriptor (5120 bytes) then fits three to a page, and a
//!   2880-value one (11520 bytes) one to a page, with no overflow pages, which keeps loading a sequential scan, split across threads ([`KeyframeStore::load_db`]).
//! - Descriptors are little-endian `f32` blobs; stamps are nanoseconds; ids are SQLite integers, so ids
//!   above `i64::MAX` are refused. Rows keep insertion order (`seq`), which is the detector's history order.
//! - Beside the file, `<db>-vectors` holds the descriptors again as one raw matrix, which a load maps
//!   instead of copying ([`vectors`]: derived data, checked before use and rebuilt from the database
//!   when it does not check out). It doubles the disk space the descriptors take, for a load that takes
//!   no new memory: 0.1-0.2 s for 100k 1280-value keyframes however dear fresh memory is.
//!
//! Local features: with verification on, each keyframe's local features (an opaque blob the
//! verification stage writes, about 22 KB for 500 ORB features) go into `local_features` in the
//! keyframe's transaction, and a depth image that arrives later updates them; a restart gives the
//! newest back to verification, so loops to keyframes stored before it are still verified.
//!
//! Frames and tracker poses: a keyframe's camera `frame_id` and, where the tracker gave one, its pose
//! in the tracker's map go into `frames` with it, so a restarted node still names the match's frame
//! and draws loop edges to keyframes stored before the restart.
//!
//! Temporal consistency: where it is on, what it remembers after a keyframe (the last queries'
//! matches, held back or not) replaces the previous keyframe's in `consistency`, in the keyframe's
//! transaction, so a restart goes on with it: a loop held back before the restart is reported once a
//! keyframe after it confirms the loop, as without the restart.
//!
//! Identity: a store records the weights' SHA-256, the architecture, the descriptor mode, the input size
//! and the descriptor length ([`StoreIdentity`]); descriptors from any other combination are not
//! comparable, so opening a store with a different identity is refused with both identities named.
//!
//! Merging ([`merge`]) concatenates two sessions of the same identity: the first store's keyframes,
//! then the second's, ids kept (or the second's shifted by an offset); an id found in both is an error
//! that names the clashing ids.

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};

use crate::types::LoopCandidate;
use nalgebra::Isometry3;
use rusqlite::{params, Connection, OpenFlags, OptionalExtension};

use crate::detector::rows::DescriptorRows;
use crate::detector::KeyframeDb;
use crate::types::Stamp;

#[cfg(unix)]
mod vectors;
#[cfg(unix)]
use vectors::VectorFile;

/// Fewer rows than this per thread are not worth a thread of their own when loading.
const LOAD_ROWS_PER_THREAD_MIN: usize = 4096;
/// Rows `db merge` reads at a time to fill the merged store's vector file (tens of MB).
const MERGE_ROWS_PER_STEP: usize = 4096;

/// Written into every store; a file with another format value is refused.
const FORMAT: &str = "ecm-lcd keyframes 1";

/// What the stored descriptors were computed with; two stores (or a store and a pipeline) can share
/// keyframes only when these are equal.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoreIdentity {
    /// SHA-256 of the weights file, lower-case hex.
    pub weights_sha256: String,
    pub arch: String,
    pub descriptor_mode: String,
    pub input_size: usize,
    /// Values per descriptor.
    pub dim: usize,
}

impl std::fmt::Display for StoreIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "weights sha256 {}, arch {}, descriptor {} ({} values), input {}",
            self.weights_sha256, self.arch, self.descriptor_mode, self.dim, self.input_size
        )
    }
}

impl StoreIdentity {
    /// Ok when `other` equals `self`; otherwise an error naming both (`what_self`, `what_other` say
    /// whose identity each is).
    pub fn check_same(&self, what_self: &str, other: &StoreIdentity, what_other: &str) -> Result<()> {
        if self != other {
            bail!("{what_self} has keyframes of [{self}], but {what_other} has [{other}]; their descriptors are not comparable");
        }
        Ok(())
    }
}

/// One stored keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredKeyframe {
    pub id: u64,
    pub stamp: Stamp,
    pub descriptor: Vec<f32>,
}

/// Counts and ranges of a store (`ecm-lcd db info`).
#[derive(Clone, Debug, PartialEq)]
pub struct StoreSummary {
    pub count: u64,
    /// Smallest and largest id.
    pub ids: Option<(u64, u64)>,
    /// Earliest and latest stamp.
    pub stamps: Option<(Stamp, Stamp)>,
    /// Bytes on disk: the database file, its write-ahead log and its vector file.
    pub bytes: u64,
}

/// An open keyframe store (module doc).
pub struct KeyframeStore {
    connection: Connection,
    path: PathBuf,
    identity: StoreIdentity,
    count: u64,
    max_id: Option<u64>,
    /// Unique per database file (the `uid` meta entry): ties a vector file to its database.
    uid: [u8; 32],
    /// The vector file, opened at the first append.
    #[cfg(unix)]
    vectors: Option<VectorFile>,
}

impl std::fmt::Debug for KeyframeStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "KeyframeStore({}, {} keyframes)", self.path.display(), self.count)
    }
}

/// The suffixes of the files SQLite and the vector file keep beside a store (`<db>-wal`, ...).
pub const FILES_BESIDE: [&str; 3] = ["-wal", "-shm", "-vectors"];

/// A read-only connection to the store at `path` ([`read_only_uri`]: immutable where it is at rest).
fn open_for_reading(path: &Path) -> Result<Connection> {
    let flags = OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX;
    match read_only_uri(path) {
        Ok(uri) => open_connection(Path::new(&uri), flags | OpenFlags::SQLITE_OPEN_URI)
            .with_context(|| format!("cannot open keyframe database {}", path.display())),
        // A path a URI cannot spell (not UTF-8) is opened by name.
        Err(_) => open_connection(path, flags),
    }
}

fn open_connection(path: &Path, flags: OpenFlags) -> Result<Connection> {
    let connection = Connection::open_with_flags(path, flags)
        .with_context(|| format!("cannot open keyframe database {}", path.display()))?;
    // The writer holds the lock only for one insert; a reader (db info on a running node) waits for it.
    connection.busy_timeout(std::time::Duration::from_secs(5))?;
    Ok(connection)
}

/// Whether `path` looks like a keyframe database (`--db`): a regular file in SQLite's format that is
/// not a ROS 2 bag (`.db3`).
pub fn is_keyframe_store(path: &Path) -> bool {
    use std::io::Read;
    if !path.is_file() || path.extension().is_some_and(|e| e.eq_ignore_ascii_case("db3")) {
        return false;
    }
    let mut magic = [0u8; 16];
    std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut magic)).is_ok() && &magic == b"SQLite format 3\0"
}

/// An existing regular file (a symlink to one is followed), or an error that says what it is.
fn ensure_database_file(path: &Path) -> Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => Ok(()),
        Ok(m) if m.is_dir() => bail!("keyframe database {} is a directory", path.display()),
        Ok(_) => bail!("keyframe database {} is not a regular file", path.display()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("keyframe database {} does not exist", path.display())
        }
        Err(e) => Err(e).with_context(|| format!("cannot open keyframe database {}", path.display())),
    }
}

fn to_sql_id(id: u64) -> Result<i64> {
    i64::try_from(id).with_context(|| format!("keyframe id {id} is too large for the database (at most {})", i64::MAX))
}

fn descriptor_blob(descriptor: &[f32]) -> Vec<u8> {
    descriptor.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A pose as 7 little-endian `f64`: translation x, y, z, then the rotation quaternion i, j, k, w.
fn pose_blob(pose: &Isometry3<f64>) -> Vec<u8> {
    let (t, q) = (pose.translation.vector, pose.rotation.coords);
    [t.x, t.y, t.z, q.x, q.y, q.z, q.w].iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn pose_from_blob(blob: &[u8]) -> Result<Isometry3<f64>> {
    ensure!(blob.len() == 56, "a pose takes 56 bytes, not {}", blob.len());
    let v: Vec<f64> = blob.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))).collect();
    let rotation = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]));
    Ok(Isometry3::from_parts(nalgebra::Translation3::new(v[0], v[1], v[2]), rotation))
}

/// One keyframe as [`KeyframeStore::append_keyframe`] commits it, in one transaction.
#[derive(Clone, Copy, Debug)]
pub struct KeyframeRecord<'a> {
    pub id: u64,
    pub stamp: Stamp,
    pub descriptor: &'a [f32],
    /// The loop candidates reported when it was processed: its own, and those of earlier keyframes
    /// that temporal consistency held back and it confirmed (their own `query_id`).
    pub candidates: &'a [LoopCandidate],
    /// Its local features, as the verification stage writes them (opaque here).
    pub local_features: Option<&'a [u8]>,
    /// The camera frame its image came in (empty: unknown).
    pub frame_id: &'a str,
    /// The camera's pose in the tracker's map (world_T_camera), where the tracker gave one.
    pub tracker_pose: Option<Isometry3<f64>>,
    /// What temporal consistency remembers after this keyframe, where it is on (opaque here).
    pub consistency: Option<&'a str>,
}

impl<'a> KeyframeRecord<'a> {
    /// A keyframe with nothing beside its descriptor.
    pub fn new(id: u64, stamp: Stamp, descriptor: &'a [f32]) -> Self {
        KeyframeRecord {
            id,
            stamp,
            descriptor,
            candidates: &[],
            local_features: None,
            frame_id: "",
            tracker_pose: None,
            consistency: None,
        }
    }
}

impl KeyframeStore {
    /// Opens the store at `path`, creating it for `identity` when the file does not exist or is empty;
    /// an existing store must have exactly `identity` (module doc). A new store is built under a
    /// temporary name and renamed into place, so a crash while creating never leaves a file at `path`
    /// that is not a complete, empty store.
    pub fn open_or_create(path: &Path, identity: &StoreIdentity) -> Result<Self> {
        // A symlink is written through (the store is created at its target, the link stays).
        let target;
        let path = if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
            target = std::fs::canonicalize(path)
                .with_context(|| format!("keyframe database {} is a dangling symlink", path.display()))?;
            target.as_path()
        } else {
            path
        };
        // Only a missing path or an empty regular file is created; a device, FIFO or directory is
        // refused rather than replaced.
        let created = match std::fs::metadata(path) {
            Err(_) => true,
            Ok(m) if m.is_file() => m.len() == 0,
            Ok(_) => bail!("keyframe database {} is not a regular file; give a file path", path.display()),
        };
        if created {
            refuse_orphaned_log(path)?;
            create_store_file(path, identity)
                .with_context(|| format!("creating keyframe database {}", path.display()))?;
        }
        let connection = open_connection(path, OpenFlags::SQLITE_OPEN_READ_WRITE)?;
        let store = Self::from_connection(connection, path, true)?;
        store.identity.check_same(&format!("keyframe database {}", path.display()), identity, "this pipeline")?;
        #[cfg(unix)]
        if created {
            // Without it (a crash just here) the first load writes it.
            VectorFile::create_empty(&vectors::path_for(path), identity.dim, store.uid)?;
        }
        Ok(store)
    }

    /// Opens an existing store for writing, whatever its identity.
    pub fn open_existing(path: &Path) -> Result<Self> {
        ensure_database_file(path)?;
        let connection = open_connection(path, OpenFlags::SQLITE_OPEN_READ_WRITE)?;
        Self::from_connection(connection, path, true)
    }

    /// Opens an existing store for reading only (inspection, export, the inputs of a merge): the
    /// file is never created, converted or modified, and no file is created beside it. A store in
    /// use (its write-ahead log is there) is read through the log, as a writer sees it; one at rest
    /// is opened immutable, which needs no shared-memory file and works on a read-only file system.
    pub fn open_read_only(path: &Path) -> Result<Self> {
        ensure_database_file(path)?;
        Self::from_connection(open_for_reading(path)?, path, false)
    }

    fn from_connection(connection: Connection, path: &Path, writable: bool) -> Result<Self> {
        let context = || format!("keyframe database {}", path.display());
        if writable {
            // WAL and FULL: see the module doc. journal_mode is stored in the file; synchronous is per connection.
            connection
                .query_row("PRAGMA journal_mode = WAL", [], |r| r.get::<_, String>(0))
                .with_context(|| format!("{} is not a keyframe database (or is damaged)", path.display()))?;
            connection.pragma_update(None, "synchronous", "FULL").with_context(context)?;
            // Stores made before candidates (or local features) were stored get the table (and keep
            // no `all` mark).
            connection
                .execute_batch(
                    "CREATE TABLE IF NOT EXISTS candidates (query_id INTEGER PRIMARY KEY, json TEXT NOT NULL);
                     CREATE TABLE IF NOT EXISTS local_features (id INTEGER PRIMARY KEY, data BLOB NOT NULL);
                     CREATE TABLE IF NOT EXISTS frames (id INTEGER PRIMARY KEY, frame_id TEXT NOT NULL, pose BLOB);
                     CREATE TABLE IF NOT EXISTS consistency (id INTEGER PRIMARY KEY, json TEXT NOT NULL);",
                )
                .with_context(context)?;
        }
        let meta = |key: &str| -> Result<String> {
            connection
                .query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get::<_, String>(0))
                .optional()
                .with_context(|| format!("{} is not a keyframe database (or is damaged)", path.display()))?
                .with_context(|| format!("{}: no `{key}` entry in its meta table", context()))
        };
        let format = meta("format")?;
        ensure!(format == FORMAT, "{}: format {format:?}, this program reads {FORMAT:?}", context());
        let number = |key: &str| -> Result<usize> {
            let text = meta(key)?;
            text.parse().with_context(|| format!("{}: `{key}` is {text:?}, not a number", context()))
        };
        let identity = StoreIdentity {
            weights_sha256: meta("weights_sha256")?,
            arch: meta("arch")?,
            descriptor_mode: meta("descriptor_mode")?,
            input_size: number("input_size")?,
            dim: number("dim")?,
        };
        let (count, max_id): (i64, Option<i64>) = connection
            .query_row("SELECT count(*), max(id) FROM keyframes", [], |r| Ok((r.get(0)?, r.get(1)?)))
            .with_context(context)?;
        // Stores written before the vector file have no uid: they get one now (first writer wins);
        // read-only, one that is not there is all zeros (it only names the vector file's owner).
        if !writable && meta("uid").is_err() {
            return Ok(KeyframeStore {
                connection,
                path: path.to_path_buf(),
                identity,
                count: count as u64,
                max_id: max_id.map(|id| id as u64),
                uid: [b'0'; 32],
                #[cfg(unix)]
                vectors: None,
            });
        }
        if meta("uid").is_err() {
            connection
                .execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('uid', ?1)", [new_uid(path)])
                .with_context(|| format!("{}: recording its unique id", context()))?;
        }
        let uid = meta("uid")?;
        let uid = <[u8; 32]>::try_from(uid.as_bytes())
            .ok()
            .with_context(|| format!("{}: its uid {uid:?} is not 32 characters", context()))?;
        Ok(KeyframeStore {
            connection,
            path: path.to_path_buf(),
            identity,
            count: count as u64,
            max_id: max_id.map(|id| id as u64),
            uid,
            #[cfg(unix)]
            vectors: None,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn identity(&self) -> &StoreIdentity {
        &self.identity
    }

    /// Keyframes stored.
    pub fn len(&self) -> u64 {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The largest stored id (a restart continues after it).
    pub fn max_id(&self) -> Option<u64> {
        self.max_id
    }

    /// Appends one keyframe in its own committed transaction: when this returns Ok the keyframe is on
    /// disk (fsynced). Refuses a descriptor of the wrong length or with a non-finite value, and an id
    /// that is already stored.
    pub fn append(&mut self, id: u64, stamp: Stamp, descriptor: &[f32]) -> Result<()> {
        self.append_keyframe(&KeyframeRecord::new(id, stamp, descriptor))
    }

    /// As [`KeyframeStore::append`], with the keyframe's loop candidates in the same transaction: a
    /// crash leaves both or neither, so a restarted replay can write out every candidate emitted
    /// before it ([`KeyframeStore::stored_candidates`]), and its local features, frame and tracker pose
    /// where given (module doc).
    pub fn append_keyframe(&mut self, record: &KeyframeRecord) -> Result<()> {
        let KeyframeRecord { id, stamp, descriptor, candidates, local_features, frame_id, tracker_pose, consistency } =
            *record;
        ensure!(
            descriptor.len() == self.identity.dim,
            "keyframe {id} descriptor has {} values, the database {} holds {}-value descriptors",
            descriptor.len(),
            self.path.display(),
            self.identity.dim
        );
        if let Some(i) = descriptor.iter().position(|x| !x.is_finite()) {
            bail!("keyframe {id} descriptor value {i} is {} (not finite)", descriptor[i]);
        }
        let sql_id = to_sql_id(id)?;
        let json = if candidates.is_empty() { None } else { Some(serde_json::to_string(candidates)?) };
        let written = (|| -> rusqlite::Result<i64> {
            let transaction = self.connection.transaction()?;
            transaction
                .prepare("INSERT INTO keyframes (id, stamp_nanos, descriptor) VALUES (?1, ?2, ?3)")?
                .execute(params![sql_id, stamp.nanos, descriptor_blob(descriptor)])?;
            // The keyframe's row, read before the other tables' inserts move the last row id on.
            let seq = transaction.last_insert_rowid();
            if let Some(json) = &json {
                transaction
                    .prepare("INSERT OR REPLACE INTO candidates (query_id, json) VALUES (?1, ?2)")?
                    .execute(params![sql_id, json])?;
            }
            if let Some(features) = local_features {
                transaction
                    .prepare("INSERT OR REPLACE INTO local_features (id, data) VALUES (?1, ?2)")?
                    .execute(params![sql_id, features])?;
            }
            if !frame_id.is_empty() || tracker_pose.is_some() {
                transaction
                    .prepare("INSERT OR REPLACE INTO frames (id, frame_id, pose) VALUES (?1, ?2, ?3)")?
                    .execute(params![sql_id, frame_id, tracker_pose.map(|p| pose_blob(&p))])?;
            }
            if let Some(json) = consistency {
                // Only the newest keyframe's is worth keeping.
                transaction.execute("DELETE FROM consistency", [])?;
                transaction
                    .prepare("INSERT INTO consistency (id, json) VALUES (?1, ?2)")?
                    .execute(params![sql_id, json])?;
            }
            transaction.commit()?;
            Ok(seq)
        })();
        let seq = match written {
            Ok(seq) => seq,
            Err(rusqlite::Error::SqliteFailure(e, _)) if e.code == rusqlite::ErrorCode::ConstraintViolation => {
                bail!("keyframe id {id} is already stored in {}", self.path.display())
            }
            Err(e) => return Err(e).with_context(|| format!("storing keyframe {id} in {}", self.path.display())),
        };
        self.count += 1;
        self.max_id = Some(self.max_id.map_or(id, |m| m.max(id)));
        self.extend_vector_file(seq, seq, descriptor);
        Ok(())
    }

    /// Replaces stored keyframe `id`'s local features (a depth image that came after it).
    pub fn update_local_features(&mut self, id: u64, local_features: &[u8]) -> Result<()> {
        let changed = self
            .connection
            .execute("UPDATE local_features SET data = ?2 WHERE id = ?1", params![to_sql_id(id)?, local_features])
            .with_context(|| format!("updating the local features of keyframe {id} in {}", self.path.display()))?;
        ensure!(changed == 1, "keyframe {id} has no stored local features in {}", self.path.display());
        Ok(())
    }

    /// The stored local features of the newest `newest` keyframes that have them (0: all), oldest first.
    pub fn local_features(&self, newest: usize) -> Result<Vec<(u64, Vec<u8>)>> {
        self.newest_rows("local_features", "data", newest, |r| r.get(1))
    }

    /// The stored camera frame and tracker pose of the newest `newest` keyframes that have them (0:
    /// all), oldest first.
    pub fn frames(&self, newest: usize) -> Result<Vec<(u64, (String, Option<Isometry3<f64>>))>> {
        let rows = self.newest_rows("frames", "frame_id, f.pose", newest, |r| {
            Ok((r.get::<_, String>(1)?, r.get::<_, Option<Vec<u8>>>(2)?))
        })?;
        rows.into_iter()
            .map(|(id, (frame_id, pose))| {
                let pose = pose
                    .map(|blob| pose_from_blob(&blob))
                    .transpose()
                    .with_context(|| format!("keyframe {id}'s tracker pose in {}", self.path.display()))?;
                Ok((id, (frame_id, pose)))
            })
            .collect()
    }

    /// `(id, value)` of the newest `newest` keyframes (0: all) with a row in `table`, oldest first;
    /// `value` is read from the columns after the id (`f.` is the table). Empty when a store written
    /// before the table existed is opened read-only.
    fn newest_rows<T>(
        &self,
        table: &str,
        columns: &str,
        newest: usize,
        value: impl Fn(&rusqlite::Row) -> rusqlite::Result<T>,
    ) -> Result<Vec<(u64, T)>> {
        let context = || format!("reading {table} in {}", self.path.display());
        let exists: Option<String> = self
            .connection
            .query_row("SELECT name FROM sqlite_master WHERE type = 'table' AND name = ?1", [table], |r| r.get(0))
            .optional()
            .with_context(context)?;
        if exists.is_none() {
            return Ok(Vec::new());
        }
        let limit = if newest == 0 { -1 } else { i64::try_from(newest).unwrap_or(i64::MAX) };
        let sql = format!(
            "SELECT k.id, f.{columns} FROM keyframes k JOIN {table} f ON f.id = k.id ORDER BY k.seq DESC LIMIT ?1"
        );
        let mut statement = self.connection.prepare(&sql).with_context(context)?;
        let mut rows: Vec<(u64, T)> = statement
            .query_map([limit], |r| Ok((r.get::<_, i64>(0)? as u64, value(r)?)))
            .with_context(context)?
            .collect::<rusqlite::Result<_>>()
            .with_context(context)?;
        rows.reverse();
        Ok(rows)
    }

    /// Whether keyframe `id` is stored.
    pub fn contains(&self, id: u64) -> Result<bool> {
        let sql_id = to_sql_id(id)?;
        Ok(self
            .connection
            .query_row("SELECT 1 FROM keyframes WHERE id = ?1", [sql_id], |_| Ok(()))
            .optional()
            .with_context(|| format!("looking up keyframe {id} in {}", self.path.display()))?
            .is_some())
    }

    /// The parameters the stored keyframes were processed with, as the last run to continue the
    /// store recorded them (JSON text, [`KeyframeStore::record_parameters`]); `None` where no run
    /// did (a store made before they were recorded).
    pub fn recorded_parameters(&self) -> Result<Option<String>> {
        self.connection
            .query_row("SELECT value FROM meta WHERE key = 'parameters'", [], |r| r.get::<_, String>(0))
            .optional()
            .with_context(|| format!("reading the parameters recorded in {}", self.path.display()))
    }

    /// Records `json` as the parameters the keyframes from now on are processed with.
    pub fn record_parameters(&mut self, json: &str) -> Result<()> {
        self.connection
            .execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('parameters', ?1)", [json])
            .with_context(|| format!("recording the parameters in {}", self.path.display()))?;
        Ok(())
    }

    /// Every stored keyframe's candidates, in the order the keyframes were stored; `None` when the
    /// store does not hold them all (made before candidates were stored, or merged).
    pub fn stored_candidates(&self) -> Result<Option<Vec<LoopCandidate>>> {
        let complete = self
            .connection
            .query_row("SELECT value FROM meta WHERE key = 'candidates'", [], |r| r.get::<_, String>(0))
            .optional()?
            .is_some_and(|v| v == CANDIDATES_ALL);
        if !complete {
            return Ok(None);
        }
        let context = || format!("reading the candidates stored in {}", self.path.display());
        let mut query = self
            .connection
            .prepare("SELECT c.json FROM candidates c JOIN keyframes k ON k.id = c.query_id ORDER BY k.seq")
            .with_context(context)?;
        let mut all = Vec::new();
        for json in query.query_map([], |r| r.get::<_, String>(0)).with_context(context)? {
            let batch: Vec<LoopCandidate> = serde_json::from_str(&json.with_context(context)?).with_context(context)?;
            all.extend(batch);
        }
        Ok(Some(all))
    }

    /// The newest stored keyframe (id, stamp, descriptor), `None` when the store is empty.
    pub fn last_keyframe(&self) -> Result<Option<(u64, Stamp, Vec<f32>)>> {
        Ok(self.last_keyframes(1)?.pop())
    }

    /// The newest `count` stored keyframes (fewer where fewer are stored), oldest first.
    pub fn last_keyframes(&self, count: usize) -> Result<Vec<(u64, Stamp, Vec<f32>)>> {
        let mut last = Vec::new();
        self.for_each(self.count.saturating_sub(count as u64), |id, stamp, blob| {
            last.push((id, stamp, decode_descriptor(blob).collect()));
            Ok(())
        })?;
        Ok(last)
    }

    /// What temporal consistency remembered after the newest keyframe that stored it, with that
    /// keyframe's id ([`KeyframeRecord::consistency`]).
    pub fn consistency(&self) -> Result<Option<(u64, String)>> {
        self.connection
            .query_row("SELECT id, json FROM consistency", [], |r| Ok((r.get::<_, i64>(0)? as u64, r.get(1)?)))
            .optional()
            .with_context(|| format!("reading keyframe database {}", self.path.display()))
    }

    /// Calls `each` with every stored keyframe in insertion order, skipping the first `skip`.
    pub fn for_each(&self, skip: u64, each: impl FnMut(u64, Stamp, &[u8]) -> Result<()>) -> Result<()> {
        match self.seq_at(skip)? {
            Some(first_seq) => {
                scan_rows(&self.connection, &self.path, self.identity.dim, first_seq, None, Columns::All, each)
            }
            None => Ok(()),
        }
    }

    /// The `seq` of the row at position `position` in insertion order (`None` past the end).
    fn seq_at(&self, position: u64) -> Result<Option<i64>> {
        let context = || format!("reading keyframe database {}", self.path.display());
        if position >= self.count {
            return Ok(None);
        }
        // Rows are never deleted, so seq normally runs without gaps and the position is arithmetic;
        // otherwise SQLite steps through the rows before it.
        let (first, last): (Option<i64>, Option<i64>) = self
            .connection
            .query_row("SELECT min(seq), max(seq) FROM keyframes", [], |r| Ok((r.get(0)?, r.get(1)?)))
            .with_context(context)?;
        if let Some((first, last)) = first.zip(last).filter(|(first, last)| (last - first) as u64 + 1 == self.count) {
            return Ok(Some(first + position as i64).filter(|&seq| seq <= last));
        }
        self.connection
            .query_row("SELECT seq FROM keyframes ORDER BY seq LIMIT 1 OFFSET ?1", [position as i64], |r| r.get(0))
            .optional()
            .with_context(context)
    }

    /// Every stored keyframe, in insertion order (small stores; the detector loads with [`KeyframeStore::load_db`]).
    pub fn keyframes(&self) -> Result<Vec<StoredKeyframe>> {
        let mut out = Vec::with_capacity(self.count as usize);
        self.for_each(0, |id, stamp, blob| {
            out.push(StoredKeyframe { id, stamp, descriptor: decode_descriptor(blob).collect() });
            Ok(())
        })?;
        Ok(out)
    }

    /// The newest `limit` keyframes (all of them when `limit` is `None`) as a detector database, in
    /// insertion order.
    ///
    /// The descriptors come from the vector file, mapped ([`vectors`]), once it checks out; rows it
    /// lacks are read from the database and appended to it (all of them when it had to be rebuilt).
    /// Reading from the database is split into one contiguous range of rows per rayon thread, each
    /// read through a connection of its own straight into its part of the result.
    pub fn load_db(&self, limit: Option<usize>) -> Result<KeyframeDb> {
        self.load_db_on(limit, rayon::current_num_threads())
    }

    /// [`KeyframeStore::load_db`] on at most `threads` threads.
    fn load_db_on(&self, limit: Option<usize>, threads: usize) -> Result<KeyframeDb> {
        let skip = match limit {
            Some(limit) => self.count.saturating_sub(limit as u64),
            None => 0,
        };
        let dim = self.identity.dim;
        let len = (self.count - skip) as usize;
        let (mut ids, mut stamps) = (Vec::with_capacity(len), Vec::with_capacity(len));
        let mut descriptors = DescriptorRows::with_capacity(0);
        // Rows the vector file covers (checked, mapped) come from it; the rest from the database.
        #[cfg(unix)]
        let (vector_file, covered) = match self.checked_vector_file(len * dim) {
            Some((file, header, mut rows)) => {
                if skip < header.rows {
                    (ids, stamps, _) =
                        self.read_range(skip, (header.rows - skip) as usize, threads, Columns::IdAndStamp)?;
                    rows.drain_front(skip as usize * dim);
                    descriptors = rows;
                }
                (Some((file, header)), header.rows)
            }
            None => (None, 0),
        };
        #[cfg(not(unix))]
        let covered = 0;
        if covered < self.count {
            let (tail_ids, tail_stamps, tail_values) =
                self.read_range(covered, (self.count - covered) as usize, threads, Columns::All)?;
            #[cfg(unix)]
            if let Some((file, header)) = &vector_file {
                let last_seq = self.seq_at(self.count - 1)?.context("keyframe database changed while loading")?;
                let prev_seq = (header.rows > 0).then_some(header.last_seq);
                match file.append_after(dim, &self.uid, prev_seq, last_seq, &tail_values) {
                    Ok(true) => {}
                    Ok(false) => log::warn!(
                        "keyframe database {}: its vector file changed while loading; the next load catches it up",
                        self.path.display()
                    ),
                    Err(e) => log::warn!("keyframe database {}: {e:#}", self.path.display()),
                }
            }
            let keep = skip.saturating_sub(covered) as usize;
            ids.extend_from_slice(&tail_ids[keep..]);
            stamps.extend_from_slice(&tail_stamps[keep..]);
            if descriptors.is_empty() && keep == 0 {
                descriptors = tail_values.into();
            } else {
                descriptors.extend_from_slice(&tail_values[keep * dim..]);
            }
        }
        let mut db = KeyframeDb::from_history(dim, ids, stamps, descriptors)?;
        // The index is built by whoever takes the history (`Detector::replace_history`, at start-up),
        // else by the first keyframe inserted after the load; not here, so that a load stays fast.
        db.index_at_next_insert();
        Ok(db)
    }

    /// Brings the vector file up to date with the database, reading `rows_per_step` rows at a time,
    /// so that memory stays bounded whatever the store's size (a whole [`KeyframeStore::load_db`]
    /// would hold every descriptor at once).
    #[cfg(unix)]
    fn fill_vector_file(&self, rows_per_step: usize) -> Result<()> {
        let Some((file, header, _)) = self.checked_vector_file(0) else { return Ok(()) };
        let (mut covered, mut prev_seq) = (header.rows, (header.rows > 0).then_some(header.last_seq));
        while covered < self.count {
            let len = (self.count - covered).min(rows_per_step.max(1) as u64) as usize;
            let (_, _, values) = self.read_range(covered, len, rayon::current_num_threads(), Columns::All)?;
            let last_seq = self.seq_at(covered + len as u64 - 1)?.context("keyframe database changed while reading")?;
            ensure!(
                file.append_after(self.identity.dim, &self.uid, prev_seq, last_seq, &values)?,
                "{} changed while it was filled",
                vectors::path_for(&self.path).display()
            );
            (covered, prev_seq) = (covered + len as u64, Some(last_seq));
        }
        Ok(())
    }

    /// The vector file with its header and its rows mapped, once it checks out ([`vectors`]);
    /// otherwise (the reason logged) a new empty one to rebuild, or `None` where none can be written
    /// (the load then reads every row from the database).
    #[cfg(unix)]
    fn checked_vector_file(&self, spare: usize) -> Option<(VectorFile, vectors::Header, DescriptorRows)> {
        let path = vectors::path_for(&self.path);
        if self.identity.dim == 0 {
            return None;
        }
        let checked = (|| -> Result<Option<(VectorFile, vectors::Header, DescriptorRows)>> {
            let Some(file) = VectorFile::open(&path)? else { return Ok(None) };
            let header = file.header()?;
            ensure!(header.dim as usize == self.identity.dim, "it holds {}-value rows", header.dim);
            ensure!(header.uid == self.uid, "it belongs to another database");
            ensure!(header.rows <= self.count, "it holds {} rows, the database {}", header.rows, self.count);
            if header.rows > 0 {
                let position = header.rows - 1;
                ensure!(self.seq_at(position)? == Some(header.last_seq), "its row {position} is not the database's");
                let stored: Vec<u8> = self
                    .connection
                    .query_row("SELECT descriptor FROM keyframes WHERE seq = ?1", [header.last_seq], |r| r.get(0))
                    .context("reading the database")?;
                ensure!(
                    stored == file.row(position, self.identity.dim)?,
                    "its row {position} differs from the database's"
                );
            }
            let rows = file.map_checked(&header, spare)?;
            Ok(Some((file, header, rows)))
        })();
        match checked {
            Ok(Some(found)) => return Some(found),
            Ok(None) => {
                log::info!("keyframe database {}: writing its vector file {}", self.path.display(), path.display())
            }
            Err(e) => log::warn!(
                "keyframe database {}: rebuilding its vector file {}: {e:#}",
                self.path.display(),
                path.display()
            ),
        }
        match VectorFile::create_empty(&path, self.identity.dim, self.uid).and_then(|file| Ok((file.header()?, file))) {
            Ok((header, file)) => Some((file, header, DescriptorRows::with_capacity(0))),
            Err(e) => {
                log::warn!(
                    "keyframe database {}: no vector file, loading from the database alone: {e:#}",
                    self.path.display()
                );
                None
            }
        }
    }

    /// Ids, stamps and (with [`Columns::All`]) descriptors of the `len` rows from position `first`,
    /// read on up to `threads` threads (one contiguous range and connection each).
    fn read_range(
        &self,
        first: u64,
        len: usize,
        threads: usize,
        columns: Columns,
    ) -> Result<(Vec<u64>, Vec<Stamp>, Vec<f32>)> {
        let dim = self.identity.dim;
        let threads = threads.min(len.div_ceil(LOAD_ROWS_PER_THREAD_MIN)).max(1);
        let rows_per_thread = len.div_ceil(threads).max(1);
        let mut ids = vec![0u64; len];
        let mut stamps = vec![Stamp::from_nanos(0); len];
        let mut descriptors = vec![0f32; if columns == Columns::All { len * dim } else { 0 }];
        let starts =
            (0..len).step_by(rows_per_thread).map(|row| self.seq_at(first + row as u64)).collect::<Result<Vec<_>>>()?;
        let path = self.path.as_path();
        // A store opened read-only is read so by every thread: nothing is created beside it.
        let read_only = self.connection.is_readonly(rusqlite::MAIN_DB)?;
        let descriptor_parts =
            descriptors.chunks_mut(rows_per_thread * dim.max(1)).map(Some).chain(std::iter::repeat_with(|| None));
        let parts = ids.chunks_mut(rows_per_thread).zip(stamps.chunks_mut(rows_per_thread)).zip(descriptor_parts);
        std::thread::scope(|scope| -> Result<()> {
            let mut workers = Vec::new();
            for (((ids, stamps), mut descriptors), first_seq) in parts.zip(starts) {
                let first_seq = first_seq
                    .with_context(|| format!("keyframe database {}: changed while loading", path.display()))?;
                workers.push(scope.spawn(move || -> Result<()> {
                    let connection = match read_only {
                        true => open_for_reading(path)?,
                        false => {
                            open_connection(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)?
                        }
                    };
                    if let Some(descriptors) = descriptors.as_deref_mut() {
                        prefault(descriptors);
                    }
                    let mut row = 0;
                    scan_rows(&connection, path, dim, first_seq, Some(ids.len()), columns, |id, stamp, blob| {
                        if let Some(descriptors) = descriptors.as_deref_mut() {
                            let descriptor = &mut descriptors[row * dim..(row + 1) * dim];
                            decode_descriptor_into(blob, descriptor);
                            KeyframeDb::check_descriptor(dim, descriptor, format_args!("stored keyframe {id}"))
                                .with_context(|| format!("keyframe database {}", path.display()))?;
                        }
                        (ids[row], stamps[row]) = (id, stamp);
                        row += 1;
                        Ok(())
                    })?;
                    ensure!(row == ids.len(), "keyframe database {}: changed while loading", path.display());
                    Ok(())
                }));
            }
            workers.into_iter().try_for_each(|worker| worker.join().expect("a keyframe loading thread panicked"))
        })?;
        Ok((ids, stamps, descriptors))
    }

    /// Counts, id and stamp ranges, size on disk.
    pub fn summary(&self) -> Result<StoreSummary> {
        let (min_id, max_id, min_stamp, max_stamp): (Option<i64>, Option<i64>, Option<i64>, Option<i64>) = self
            .connection
            .query_row("SELECT min(id), max(id), min(stamp_nanos), max(stamp_nanos) FROM keyframes", [], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
            })
            .with_context(|| format!("reading keyframe database {}", self.path.display()))?;
        let size = |p: &Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
        let mut wal = self.path.as_os_str().to_owned();
        wal.push("-wal");
        let mut vector_file = self.path.as_os_str().to_owned();
        vector_file.push("-vectors");
        Ok(StoreSummary {
            count: self.count,
            ids: min_id.zip(max_id).map(|(a, b)| (a as u64, b as u64)),
            stamps: min_stamp.zip(max_stamp).map(|(a, b)| (Stamp::from_nanos(a), Stamp::from_nanos(b))),
            bytes: size(&self.path) + size(Path::new(&wal)) + size(Path::new(&vector_file)),
        })
    }

    /// Appends many keyframes in one transaction (bulk copies: merging, test fixtures). Not for live
    /// keyframes, whose candidates must wait for their own commit ([`KeyframeStore::append`]).
    pub fn append_batch(&mut self, keyframes: impl IntoIterator<Item = (u64, Stamp, Vec<f32>)>) -> Result<u64> {
        let context = || format!("writing keyframe database {}", self.path.display());
        let transaction = self.connection.transaction().with_context(context)?;
        let mut added = 0u64;
        let mut max_id = self.max_id;
        let mut seqs = None;
        let keyframes = keyframes.into_iter();
        // Kept for the vector file, which is extended only after the commit.
        let mut values = Vec::with_capacity(keyframes.size_hint().0 * self.identity.dim);
        {
            let mut insert = transaction
                .prepare("INSERT INTO keyframes (id, stamp_nanos, descriptor) VALUES (?1, ?2, ?3)")
                .with_context(context)?;
            for (id, stamp, descriptor) in keyframes {
                ensure!(
                    descriptor.len() == self.identity.dim,
                    "keyframe {id}: {} values, expected {}",
                    descriptor.len(),
                    self.identity.dim
                );
                insert
                    .execute(params![to_sql_id(id)?, stamp.nanos, descriptor_blob(&descriptor)])
                    .with_context(|| format!("{}: keyframe {id}", context()))?;
                let seq = transaction.last_insert_rowid();
                seqs = Some((seqs.map_or(seq, |(first, _)| first), seq));
                values.extend_from_slice(&descriptor);
                added += 1;
                max_id = Some(max_id.map_or(id, |m| m.max(id)));
            }
        }
        transaction.commit().with_context(context)?;
        self.count += added;
        self.max_id = max_id;
        if let Some((first, last)) = seqs {
            self.extend_vector_file(first, last, &values);
        }
        Ok(added)
    }

    /// After the commit of the rows `first_seq..=last_seq` (`values`, whole descriptors in order),
    /// appends them to the vector file when it ends just before them ([`vectors`]); a failure only
    /// warns, as the rows are stored and the next load catches the file up.
    fn extend_vector_file(&mut self, first_seq: i64, last_seq: i64, values: &[f32]) {
        #[cfg(unix)]
        {
            let extended = (|| -> Result<()> {
                if self.vectors.as_ref().is_none_or(|file| !file.is_current()) {
                    self.vectors = VectorFile::open(&vectors::path_for(&self.path))?;
                }
                let Some(file) = &self.vectors else { return Ok(()) };
                let prev_seq: Option<i64> =
                    self.connection
                        .query_row("SELECT max(seq) FROM keyframes WHERE seq < ?1", [first_seq], |r| r.get(0))?;
                file.append_after(self.identity.dim, &self.uid, prev_seq, last_seq, values)?;
                Ok(())
            })();
            if let Err(e) = extended {
                log::warn!(
                    "keyframe database {}: vector file not extended (the next load rebuilds it): {e:#}",
                    self.path.display()
                );
            }
        }
        #[cfg(not(unix))]
        let _ = (first_seq, last_seq, values);
    }
}

/// A new unique id for a database file: 32 hex digits of a hash of the time, process and path.
fn new_uid(path: &Path) -> String {
    use sha2::Digest;
    let seed = format!("{:?} {} {}", std::time::SystemTime::now(), std::process::id(), path.display());
    sha2::Sha256::digest(seed.as_bytes()).iter().take(16).map(|b| format!("{b:02x}")).collect()
}

/// Which columns [`scan_rows`] reads.
#[derive(Clone, Copy, PartialEq)]
enum Columns {
    All,
    /// Not the descriptor (`each` gets an empty blob).
    IdAndStamp,
}

/// Calls `each` with the stored keyframes from the row whose `seq` is `first_seq` on, in insertion
/// order, at most `limit` of them (all when `None`); checks every descriptor's length.
fn scan_rows(
    connection: &Connection,
    path: &Path,
    dim: usize,
    first_seq: i64,
    limit: Option<usize>,
    columns: Columns,
    mut each: impl FnMut(u64, Stamp, &[u8]) -> Result<()>,
) -> Result<()> {
    let context = || format!("reading keyframe database {}", path.display());
    // Reading through a memory map skips a copy per page (the whole history is read once).
    connection.query_row("PRAGMA mmap_size = 4294967296", [], |_| Ok(())).optional().with_context(context)?;
    let selected = if columns == Columns::All { "id, stamp_nanos, descriptor" } else { "id, stamp_nanos" };
    let mut query = connection
        .prepare(&format!("SELECT {selected} FROM keyframes WHERE seq >= ?1 ORDER BY seq LIMIT ?2"))
        .with_context(context)?;
    let limit = limit.map_or(-1, |l| l as i64);
    let mut rows = query.query([first_seq, limit]).with_context(context)?;
    let bytes_per_descriptor = dim * 4;
    while let Some(row) = rows.next().with_context(context)? {
        let id: i64 = row.get(0).with_context(context)?;
        let stamp = Stamp::from_nanos(row.get(1).with_context(context)?);
        if columns == Columns::IdAndStamp {
            each(id as u64, stamp, &[])?;
            continue;
        }
        let blob = row.get_ref(2).and_then(|v| Ok(v.as_blob()?)).with_context(context)?;
        ensure!(
            blob.len() == bytes_per_descriptor,
            "{}: keyframe {id} has a {}-byte descriptor, expected {bytes_per_descriptor}",
            context(),
            blob.len()
        );
        each(id as u64, stamp, blob)?;
    }
    Ok(())
}

/// Maps in the pages of `buffer` (fresh, untouched memory) with one call: the kernel then fills them in
/// a loop instead of taking one page fault per 4 KiB as they are first written, which made up about
/// a third of a large load's CPU time. Best effort: without `MADV_POPULATE_WRITE` (Linux < 5.14, other
/// systems) the pages simply fault in as before.
fn prefault(buffer: &mut [f32]) {
    #[cfg(target_os = "linux")]
    {
        const PAGE: usize = 4096;
        let start = (buffer.as_ptr() as usize).div_ceil(PAGE) * PAGE;
        let end = (buffer.as_ptr() as usize + std::mem::size_of_val(buffer)) / PAGE * PAGE;
        if end > start {
            // SAFETY: [start, end) lies inside `buffer`, which we borrow mutably; populating changes no contents.
            unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_POPULATE_WRITE) };
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = buffer;
}

/// A stored descriptor blob as `f32` values.
pub fn decode_descriptor(blob: &[u8]) -> impl Iterator<Item = f32> + '_ {
    blob.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// As [`decode_descriptor`] into `out` (of `blob.len() / 4` values): one copy on little-endian machines.
fn decode_descriptor_into(blob: &[u8], out: &mut [f32]) {
    if cfg!(target_endian = "little") {
        bytemuck::cast_slice_mut::<f32, u8>(out).copy_from_slice(blob);
    } else {
        out.iter_mut().zip(decode_descriptor(blob)).for_each(|(o, v)| *o = v);
    }
}

/// Refuses to create a store at `path` beside a write-ahead log (`-wal`) or shared-memory file (`-shm`)
/// of that name: left by a database deleted while in use, SQLite would replay the log into the new
/// file and the new store would start with another's keyframes.
fn refuse_orphaned_log(path: &Path) -> Result<()> {
    for suffix in ["-wal", "-shm"] {
        let mut file = path.as_os_str().to_owned();
        file.push(suffix);
        let file = PathBuf::from(file);
        ensure!(
            !file.exists(),
            "{} is there but its keyframe database {} is not (or is empty): a log left by a database that was \
             deleted, which a new database would take over; remove {0} (and the -wal/-shm beside it) or restore \
             the database",
            file.display(),
            path.display()
        );
    }
    Ok(())
}

/// Writes an empty store for `identity` next to `path`, then renames it to `path` (and syncs the folder).
fn create_store_file(path: &Path, identity: &StoreIdentity) -> Result<()> {
    let mut temporary = path.as_os_str().to_owned();
    temporary.push(".creating");
    let temporary = PathBuf::from(temporary);
    for suffix in ["", "-wal", "-shm"] {
        let mut stale = temporary.as_os_str().to_owned();
        stale.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(stale));
    }
    let connection = open_connection(&temporary, OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_CREATE)?;
    connection.pragma_update(None, "synchronous", "FULL")?;
    create_schema(&connection, identity)?;
    // Closing the last connection checkpoints the log into the file and removes it.
    connection.close().map_err(|(_, e)| e)?;
    std::fs::rename(&temporary, path)
        .with_context(|| format!("renaming {} to {}", temporary.display(), path.display()))?;
    let folder = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::File::open(folder).and_then(|f| f.sync_all()).with_context(|| format!("syncing {}", folder.display()))?;
    Ok(())
}

/// The `candidates` meta value of a store that holds the candidates of every keyframe it holds;
/// stores made before candidates were stored, and merged stores, hold none or some.
const CANDIDATES_ALL: &str = "all";

fn create_schema(connection: &Connection, identity: &StoreIdentity) -> Result<()> {
    // page_size only takes effect before the first table exists (module doc for the value).
    connection.pragma_update(None, "page_size", 16384)?;
    connection.query_row("PRAGMA journal_mode = WAL", [], |r| r.get::<_, String>(0))?;
    connection.execute_batch(
        "BEGIN;
         CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
         CREATE TABLE keyframes (
             seq INTEGER PRIMARY KEY,
             id INTEGER NOT NULL UNIQUE,
             stamp_nanos INTEGER NOT NULL,
             descriptor BLOB NOT NULL
         );
         CREATE TABLE candidates (query_id INTEGER PRIMARY KEY, json TEXT NOT NULL);
         CREATE TABLE local_features (id INTEGER PRIMARY KEY, data BLOB NOT NULL);
         CREATE TABLE frames (id INTEGER PRIMARY KEY, frame_id TEXT NOT NULL, pose BLOB);
         CREATE TABLE consistency (id INTEGER PRIMARY KEY, json TEXT NOT NULL);",
    )?;
    let entries = [
        // Every keyframe's candidates are stored with it ([`KeyframeStore::append_keyframe`]).
        ("candidates", CANDIDATES_ALL.to_string()),
        ("format", FORMAT.to_string()),
        ("weights_sha256", identity.weights_sha256.clone()),
        ("arch", identity.arch.clone()),
        ("descriptor_mode", identity.descriptor_mode.clone()),
        ("input_size", identity.input_size.to_string()),
        ("dim", identity.dim.to_string()),
    ];
    for (key, value) in entries {
        connection.execute("INSERT INTO meta (key, value) VALUES (?1, ?2)", params![key, value])?;
    }
    connection.execute_batch("COMMIT;")?;
    Ok(())
}

/// What [`merge`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct MergeReport {
    pub from_first: u64,
    pub from_second: u64,
    /// Of all those keyframes, how many came with their local features (verification can check a
    /// match against those only).
    pub with_local_features: u64,
}

/// Writes a new store at `output` holding `first`'s keyframes, then `second`'s with `second_id_offset`
/// added to their ids, each with its local features and its frame (name and tracker pose). Both must
/// have the same identity; an id in both (after the offset) is an error naming the clashing ids;
/// `output` must not exist yet. Rows are copied inside SQLite (no descriptor passes through memory),
/// in one transaction. Not copied: the candidates (the merged map's keyframes were never matched
/// against each other) and the temporal-consistency state (that of one stream's last keyframe).
pub fn merge(first: &Path, second: &Path, output: &Path, second_id_offset: u64) -> Result<MergeReport> {
    let a = KeyframeStore::open_read_only(first)?;
    let b = KeyframeStore::open_read_only(second)?;
    a.identity.check_same(&format!("{}", first.display()), &b.identity, &format!("{}", second.display()))?;
    ensure!(!output.exists(), "{} already exists; merge writes a new database", output.display());
    let offset = i64::try_from(second_id_offset)
        .map_err(|_| anyhow::anyhow!("the id offset {second_id_offset} is too large (at most {})", i64::MAX))?;
    if let Some(max) = b.max_id {
        ensure!(
            max.checked_add(second_id_offset).is_some_and(|m| m <= i64::MAX as u64),
            "{}: its largest id {max} plus the offset {second_id_offset} is too large",
            second.display()
        );
    }
    refuse_orphaned_log(output)?;
    let inputs = attach_inputs(
        Connection::open_with_flags(":memory:", OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_URI)?,
        first,
        second,
    )?;
    let clashes: Vec<i64> = {
        let mut query = inputs.prepare(
            "SELECT first.keyframes.id FROM second.keyframes JOIN first.keyframes ON second.keyframes.id + ?1 = first.keyframes.id ORDER BY 1",
        )?;
        let ids = query.query_map([offset], |r| r.get(0))?.collect::<rusqlite::Result<_>>()?;
        ids
    };
    if !clashes.is_empty() {
        let shown: Vec<String> = clashes.iter().take(10).map(i64::to_string).collect();
        bail!(
            "{} keyframe id(s) are in both {} and {} (second's ids + {second_id_offset}): {}{}; give the second database an id offset (e.g. --offset {})",
            clashes.len(),
            first.display(),
            second.display(),
            shown.join(", "),
            if clashes.len() > 10 { ", ..." } else { "" },
            a.max_id.map_or(0, |m| m + 1)
        );
    }
    // Built under a temporary name and renamed into place when complete, so that a merge killed
    // half-way leaves no database at `output` (an empty one would pass for a map). The name is this
    // merge's own, so that only what it made is ever removed.
    let merging = crate::io::output::unused_name_beside(output, "merging")?;
    let remove_merging = || {
        for suffix in ["", "-wal", "-shm", "-vectors"] {
            let mut p = merging.as_os_str().to_owned();
            p.push(suffix);
            let _ = std::fs::remove_file(PathBuf::from(p));
        }
    };
    drop(inputs);
    let result = (|| -> Result<MergeReport> {
        let out = KeyframeStore::open_or_create(&merging, &a.identity)?;
        // Only keyframes are merged, not their candidates.
        out.connection.execute("UPDATE meta SET value = 'partial' WHERE key = 'candidates'", [])?;
        drop(out);
        let flags = OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_URI;
        let out = attach_inputs(open_connection(&merging, flags)?, first, second)?;
        out.execute_batch("BEGIN")?;
        let copy =
            "INSERT INTO main.keyframes (id, stamp_nanos, descriptor) SELECT id + ?1, stamp_nanos, descriptor FROM";
        let from_first = out.execute(&format!("{copy} first.keyframes ORDER BY seq"), [0i64])? as u64;
        let from_second = out.execute(&format!("{copy} second.keyframes ORDER BY seq"), [offset])? as u64;
        let mut with_local_features = 0;
        for (source, shift) in [("first", 0i64), ("second", offset)] {
            // A store written before these tables existed has none to copy (opened read-only, it
            // was not given them).
            let has = |table: &str| -> rusqlite::Result<bool> {
                out.query_row(
                    &format!("SELECT count(*) FROM {source}.sqlite_master WHERE type = 'table' AND name = ?1"),
                    [table],
                    |r| r.get::<_, i64>(0).map(|n| n > 0),
                )
            };
            if has("local_features")? {
                with_local_features += out.execute(
                    &format!(
                        "INSERT INTO main.local_features (id, data) SELECT id + ?1, data FROM {source}.local_features"
                    ),
                    [shift],
                )? as u64;
            }
            if has("frames")? {
                out.execute(
                    &format!(
                        "INSERT INTO main.frames (id, frame_id, pose) SELECT id + ?1, frame_id, pose FROM {source}.frames"
                    ),
                    [shift],
                )?;
            }
        }
        out.execute_batch("COMMIT")?;
        drop(out);
        // The vector file filled now, so that the first read-only use (`match --database`) finds it
        // complete and writes nothing beside the store.
        #[cfg(unix)]
        KeyframeStore::open_existing(&merging)?.fill_vector_file(MERGE_ROWS_PER_STEP)?;
        for suffix in ["", "-vectors"] {
            let (mut from, mut to) = (merging.as_os_str().to_owned(), output.as_os_str().to_owned());
            from.push(suffix);
            to.push(suffix);
            if suffix.is_empty() || Path::new(&from).exists() {
                std::fs::rename(&from, &to).with_context(|| format!("renaming {} into place", Path::new(&from).display()))?;
            }
        }
        Ok(MergeReport { from_first, from_second, with_local_features })
    })()
    .with_context(|| format!("merging into {}", output.display()));
    if result.is_err() {
        // Leave no half-written output behind.
        remove_merging();
    }
    result
}

/// `connection` with the stores `first` and `second` attached under those names, read-only
/// ([`read_only_uri`]; the connection must take URIs).
fn attach_inputs(connection: Connection, first: &Path, second: &Path) -> Result<Connection> {
    for (name, path) in [("first", first), ("second", second)] {
        connection
            .execute(&format!("ATTACH DATABASE ?1 AS {name}"), [read_only_uri(path)?])
            .with_context(|| format!("cannot read keyframe database {}", path.display()))?;
    }
    Ok(connection)
}

/// An SQLite URI that opens the store at `path` for reading (to attach a merge's inputs): immutable
/// where it is at rest, so that nothing is created beside it and a read-only file system serves;
/// through its log where it is in use (its `-wal` is there), as [`KeyframeStore::open_read_only`].
fn read_only_uri(path: &Path) -> Result<String> {
    let text = path.to_str().with_context(|| format!("{} is not a UTF-8 path", path.display()))?;
    // `file://x/...` would name a host `x`: a path starting `//` is the path starting `/`.
    let text = match text.starts_with("//") {
        true => format!("/{}", text.trim_start_matches('/')),
        false => text.to_string(),
    };
    let mut wal = path.as_os_str().to_owned();
    wal.push("-wal");
    let escaped = text.replace('%', "%25").replace('?', "%3f").replace('#', "%23");
    Ok(match Path::new(&wal).exists() {
        true => format!("file:{escaped}?mode=ro"),
        false => format!("file:{escaped}?mode=ro&immutable=1"),
    })
}

#[cfg(test)]
mod tests;
