//! The keyframe database's speed bounds: append latency and loading 100k keyframes in under a
//! second. A test binary of its own, so that no other test runs beside it (cargo runs test binaries
//! one after the other, and a concurrent memory-heavy test doubled the load's CPU time).

use std::time::Instant;

use ecm_lcd::detector::store::{KeyframeStore, StoreIdentity};
use ecm_lcd::types::Stamp;

fn identity(dim: usize) -> StoreIdentity {
    StoreIdentity {
        weights_sha256: "ab".repeat(32),
        arch: "ecmobilenet".into(),
        descriptor_mode: "l2".into(),
        input_size: 224,
        dim,
    }
}

fn descriptor(id: u64, dim: usize) -> Vec<f32> {
    (0..dim as u64).map(|i| ((id * 7919 + i * 104_729) % 10_007) as f32 / 10_007.0 - 0.5).collect()
}

fn stamp(id: u64) -> Stamp {
    Stamp::from_nanos(1_700_000_000_000_000_000 + id as i64 * 500_000_000)
}

/// CPU seconds this process has used, all threads (Linux: /proc/self/stat, 10 ms resolution);
/// `None` elsewhere.
fn process_cpu_secs() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name: state is field 3, utime 14, stime 15.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Append latency (each a committed, fsynced transaction) and the load time of 100k 1280-value
/// keyframes, printed; the load must take under a second, as a restarted node waits for it (wall
/// time; the CPU time of all threads is printed beside it). A restart maps the descriptors from the
/// store's vector file; the first load of a store without one (written by an older version, or just
/// merged) reads them from SQLite and writes the file, which is timed and printed too.
#[test]
fn append_latency_and_loading_100k_keyframes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    let dim = 1280;
    let mut store = KeyframeStore::open_or_create(&path, &identity(dim)).unwrap();
    let mut latencies = Vec::new();
    for id in 0..100u64 {
        let d = descriptor(id, dim);
        let started = Instant::now();
        store.append(id, stamp(id), &d).unwrap();
        latencies.push(started.elapsed().as_secs_f64() * 1e3);
    }
    latencies.sort_by(f64::total_cmp);
    println!(
        "append (one fsynced transaction each): median {:.2} ms, p90 {:.2} ms, max {:.2} ms",
        latencies[50], latencies[90], latencies[99]
    );
    let total = 100_000u64;
    let one = descriptor(7, dim);
    let started = Instant::now();
    store.append_batch((100..total).map(|id| (id, stamp(id), one.clone()))).unwrap();
    println!("bulk insert of {} keyframes: {:.2} s", total - 100, started.elapsed().as_secs_f64());
    drop(store);

    // Measured on a database at rest, as after a restart: the 522 MB just written are flushed first,
    // so that the load does not compete with their write-back (which tripled its time right after a build).
    let synced = std::process::Command::new("sync").status().map(|s| s.success()).unwrap_or(false);
    assert!(synced, "sync failed");
    let store = KeyframeStore::open_existing(&path).unwrap();
    let started = Instant::now();
    let cpu_before = process_cpu_secs();
    let db = store.load_db(None).unwrap();
    let wall_secs = started.elapsed().as_secs_f64();
    let cpu_secs = process_cpu_secs().zip(cpu_before).map(|(after, before)| after - before);
    println!(
        "load of {total} keyframes x {dim} f32 ({} MB on disk) on {} threads: {wall_secs:.3} s wall, {cpu_secs:.2?} s CPU",
        store.summary().unwrap().bytes >> 20,
        rayon::current_num_threads()
    );
    assert_eq!(db.len(), total as usize);
    assert_eq!((db.id(0), db.id(total as usize - 1)), (0, total - 1));
    assert_eq!(db.descriptor(3), descriptor(3, dim).as_slice());
    assert!(db.is_mapped(), "the descriptors were not mapped from the vector file");
    assert!(wall_secs < 1.0, "loading {total} keyframes took {wall_secs:.3} s");
    drop(db);

    let mut vector_file = path.as_os_str().to_owned();
    vector_file.push("-vectors");
    std::fs::remove_file(&vector_file).unwrap();
    let started = Instant::now();
    let db = store.load_db(None).unwrap();
    println!(
        "first load without a vector file (read from SQLite, file written): {:.3} s",
        started.elapsed().as_secs_f64()
    );
    assert_eq!((db.len(), &*db.descriptor(total as usize - 1)), (total as usize, descriptor(7, dim).as_slice()));
}
