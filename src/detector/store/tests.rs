use super::*;

fn identity(dim: usize) -> StoreIdentity {
    StoreIdentity {
        weights_sha256: "ab".repeat(32),
        arch: "ecmobilenet".into(),
        descriptor_mode: "l2".into(),
        input_size: 224,
        dim,
    }
}

/// A descriptor that differs per id and per value (exact f32 round trips are checked, so no
/// transcendental functions whose last bit may depend on vectorisation).
fn descriptor(id: u64, dim: usize) -> Vec<f32> {
    (0..dim as u64).map(|i| ((id * 7919 + i * 104_729) % 10_007) as f32 / 10_007.0 - 0.5).collect()
}

fn stamp(id: u64) -> Stamp {
    Stamp::from_nanos(1_700_000_000_000_000_000 + id as i64 * 500_000_000)
}

fn store_with(path: &Path, ids: impl IntoIterator<Item = u64>, dim: usize) -> KeyframeStore {
    let mut store = KeyframeStore::open_or_create(path, &identity(dim)).unwrap();
    for id in ids {
        store.append(id, stamp(id), &descriptor(id, dim)).unwrap();
    }
    store
}

#[test]
fn keyframes_round_trip_in_insertion_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    let ids = [5u64, 2, 9, 3];
    drop(store_with(&path, ids, 16));
    let store = KeyframeStore::open_or_create(&path, &identity(16)).unwrap();
    assert_eq!((store.len(), store.max_id()), (4, Some(9)));
    let stored = store.keyframes().unwrap();
    assert_eq!(stored.iter().map(|k| k.id).collect::<Vec<_>>(), ids);
    for k in &stored {
        assert_eq!(k.stamp, stamp(k.id));
        assert_eq!(k.descriptor, descriptor(k.id, 16));
    }
    // As a detector database, whole or the newest n.
    let db = store.load_db(None).unwrap();
    assert_eq!((db.len(), db.id(0), db.id(3)), (4, 5, 3));
    assert_eq!(db.descriptor(2), descriptor(9, 16).as_slice());
    let newest = store.load_db(Some(2)).unwrap();
    assert_eq!((newest.len(), newest.id(0), newest.id(1)), (2, 9, 3));
    assert_eq!(store.load_db(Some(10)).unwrap().len(), 4);
    let summary = store.summary().unwrap();
    assert_eq!(summary.count, 4);
    assert_eq!(summary.ids, Some((2, 9)));
    assert_eq!(summary.stamps, Some((stamp(2), stamp(9))));
    assert!(summary.bytes > 0);
}

/// A load large enough to be split across threads gives every keyframe once, in order, whole or the
/// newest n, also when `seq` has gaps (then the split positions are looked up row by row).
#[test]
fn a_load_split_across_threads_keeps_every_keyframe_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    let dim = 8;
    let total = 3 * LOAD_ROWS_PER_THREAD_MIN as u64 + 17;
    let mut store = KeyframeStore::open_or_create(&path, &identity(dim)).unwrap();
    store.append_batch((0..total).map(|id| (id * 3, stamp(id), descriptor(id, dim)))).unwrap();
    let check = |store: &KeyframeStore, limit: Option<usize>| {
        let db = store.load_db_on(limit, 3).unwrap();
        let first = total - db.len() as u64;
        assert_eq!(db.len() as u64, limit.map_or(total, |l| l as u64));
        for position in 0..db.len() {
            let id = first + position as u64;
            assert_eq!((db.id(position), db.stamp(position)), (id * 3, stamp(id)), "position {position}");
            assert_eq!(db.descriptor(position), descriptor(id, dim).as_slice(), "position {position}");
        }
    };
    check(&store, None);
    check(&store, Some(LOAD_ROWS_PER_THREAD_MIN * 2 + 5));
    // Gaps in seq: renumber every row (not something the store does itself).
    store
        .connection
        .execute_batch("UPDATE keyframes SET seq = -seq; UPDATE keyframes SET seq = 100 - seq * 2;")
        .unwrap();
    check(&store, None);
    check(&store, Some(LOAD_ROWS_PER_THREAD_MIN + 1));
}

#[test]
fn a_store_of_other_weights_mode_arch_or_size_is_refused_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    drop(store_with(&path, [0, 1], 8));
    let mut other = identity(8);
    other.weights_sha256 = "cd".repeat(32);
    let err = format!("{:#}", KeyframeStore::open_or_create(&path, &other).unwrap_err());
    assert!(err.contains(&"ab".repeat(32)) && err.contains(&"cd".repeat(32)) && err.contains("kf.db"), "{err}");
    let other = StoreIdentity { descriptor_mode: "paper".into(), dim: 128, ..identity(8) };
    let err = format!("{:#}", KeyframeStore::open_or_create(&path, &other).unwrap_err());
    assert!(err.contains("descriptor l2 (8 values)") && err.contains("descriptor paper (128 values)"), "{err}");
    let other = StoreIdentity { arch: "mobilenetv2".into(), ..identity(8) };
    let err = format!("{:#}", KeyframeStore::open_or_create(&path, &other).unwrap_err());
    assert!(err.contains("arch ecmobilenet") && err.contains("arch mobilenetv2"), "{err}");
    let other = StoreIdentity { input_size: 320, ..identity(8) };
    assert!(format!("{:#}", KeyframeStore::open_or_create(&path, &other).unwrap_err()).contains("input 320"));
    // Nothing was changed by the refusals.
    assert_eq!(KeyframeStore::open_existing(&path).unwrap().keyframes().unwrap().len(), 2);
}

#[test]
fn bad_keyframes_and_files_are_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    let mut store = store_with(&path, [1], 4);
    let err = format!("{:#}", store.append(1, stamp(1), &descriptor(1, 4)).unwrap_err());
    assert!(err.contains("keyframe id 1 is already stored"), "{err}");
    assert!(format!("{:#}", store.append(2, stamp(2), &[0.0; 3]).unwrap_err()).contains("3 values"));
    assert!(format!("{:#}", store.append(2, stamp(2), &[0.0, f32::NAN, 0.0, 0.0]).unwrap_err()).contains("not finite"));
    assert!(format!("{:#}", store.append(u64::MAX, stamp(2), &[0.0; 4]).unwrap_err()).contains("too large"));
    assert_eq!((store.len(), store.max_id()), (1, Some(1)));
    drop(store);
    assert_eq!(KeyframeStore::open_existing(&path).unwrap().len(), 1);

    let text = dir.path().join("notes.txt");
    std::fs::write(&text, "query_id,match_id\n1,2\n".repeat(200)).unwrap();
    let err = format!("{:#}", KeyframeStore::open_or_create(&text, &identity(4)).unwrap_err());
    assert!(err.contains("notes.txt") && err.contains("not a keyframe database"), "{err}");
    let missing = dir.path().join("missing.db");
    assert!(format!("{:#}", KeyframeStore::open_existing(&missing).unwrap_err()).contains("missing.db"));
    assert!(!missing.exists());
    // Another SQLite file (say, a ROS 2 bag) is not a keyframe database either.
    let other = dir.path().join("other.db3");
    Connection::open(&other).unwrap().execute_batch("CREATE TABLE meta (key TEXT, value TEXT);").unwrap();
    assert!(format!("{:#}", KeyframeStore::open_existing(&other).unwrap_err()).contains("no `format` entry"));
}

#[test]
fn merge_keeps_ids_refuses_clashes_and_other_identities() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, out) = (dir.path().join("a.db"), dir.path().join("b.db"), dir.path().join("out.db"));
    drop(store_with(&a, 0..5, 8));
    drop(store_with(&b, 3..7, 8));
    let err = format!("{:#}", merge(&a, &b, &out, 0).unwrap_err());
    assert!(err.contains("2 keyframe id(s)") && err.contains("3, 4") && err.contains("--offset 5"), "{err}");
    assert!(!out.exists());

    let report = merge(&a, &b, &out, 100).unwrap();
    assert_eq!(report, MergeReport { from_first: 5, from_second: 4, with_local_features: 0 });
    let merged = KeyframeStore::open_existing(&out).unwrap();
    assert_eq!(merged.identity(), &identity(8));
    let keyframes = merged.keyframes().unwrap();
    assert_eq!(keyframes.iter().map(|k| k.id).collect::<Vec<_>>(), [0, 1, 2, 3, 4, 103, 104, 105, 106]);
    assert_eq!(keyframes[5].descriptor, descriptor(3, 8));
    assert_eq!(keyframes[5].stamp, stamp(3));
    assert!(format!("{:#}", merge(&a, &b, &out, 100).unwrap_err()).contains("already exists"));

    let c = dir.path().join("c.db");
    let mut other =
        KeyframeStore::open_or_create(&c, &StoreIdentity { weights_sha256: "ef".repeat(32), ..identity(8) }).unwrap();
    other.append(50, stamp(50), &descriptor(50, 8)).unwrap();
    drop(other);
    let out2 = dir.path().join("out2.db");
    let err = format!("{:#}", merge(&a, &c, &out2, 0).unwrap_err());
    assert!(err.contains(&"ab".repeat(32)) && err.contains(&"ef".repeat(32)), "{err}");
    assert!(!out2.exists());
}

/// A merge writes nothing beside its inputs (they may lie on a read-only disk), leaves no half-made
/// file, and its output is complete: a read-only load writes nothing beside it either. A store is not
/// created over a log left by a deleted one.
#[test]
fn merge_touches_no_input_and_no_store_takes_over_an_orphaned_log() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, out) = (dir.path().join("a.db"), dir.path().join("b.db"), dir.path().join("out.db"));
    drop(store_with(&a, 0..5, 8));
    drop(store_with(&b, 0..4, 8));
    let listing = || {
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let before = listing();
    merge(&a, &b, &out, 100).unwrap();
    let mut expected = before.clone();
    expected.extend(["out.db".to_string(), "out.db-vectors".to_string()]);
    expected.sort();
    assert_eq!(listing(), expected);
    let vectors = std::fs::metadata(dir.path().join("out.db-vectors")).unwrap().len();
    #[cfg(unix)]
    assert_eq!(vector_rows(&out), 9);
    assert_eq!(KeyframeStore::open_read_only(&out).unwrap().load_db(None).unwrap().len(), 9);
    assert_eq!(listing(), expected, "a read-only load wrote beside the merged store");
    assert_eq!(std::fs::metadata(dir.path().join("out.db-vectors")).unwrap().len(), vectors);

    // The log of a store deleted while in use is refused, not replayed into a new store.
    let orphan = dir.path().join("orphan.db");
    let mut store = KeyframeStore::open_or_create(&orphan, &identity(8)).unwrap();
    store.append(7, stamp(7), &descriptor(7, 8)).unwrap();
    std::fs::copy(dir.path().join("orphan.db-wal"), dir.path().join("saved-wal")).unwrap();
    drop(store);
    std::fs::remove_file(&orphan).unwrap();
    std::fs::copy(dir.path().join("saved-wal"), dir.path().join("orphan.db-wal")).unwrap();
    let err = format!("{:#}", KeyframeStore::open_or_create(&orphan, &identity(8)).unwrap_err());
    assert!(err.contains("orphan.db-wal is there") && err.contains("remove"), "{err}");
    assert!(!orphan.exists());
    let err = format!("{:#}", merge(&a, &b, &orphan, 100).unwrap_err());
    assert!(err.contains("orphan.db-wal is there"), "{err}");
    assert!(dir.path().join("orphan.db-wal").exists(), "the refusal removed the log");
    // A path written with a doubled leading slash is the same path, not a URI's host.
    let doubled = PathBuf::from(format!("/{}", out.display()));
    assert_eq!(KeyframeStore::open_read_only(&doubled).unwrap().len(), 9);
    let err = format!("{:#}", merge(&a, &b, &dir.path().join("big.db"), u64::MAX).unwrap_err());
    assert!(err.contains("the id offset 18446744073709551615 is too large"), "{err}");
}

/// A merged map verifies as its parts did: each keyframe's local features and frame come with it,
/// under its new id.
#[test]
fn merge_keeps_each_keyframes_local_features_and_frame() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, out) = (dir.path().join("a.db"), dir.path().join("b.db"), dir.path().join("out.db"));
    let pose = Isometry3::translation(1.0, 2.0, 3.0);
    for (path, ids) in [(&a, 0..3u64), (&b, 0..2)] {
        let mut store = KeyframeStore::open_or_create(path, &identity(4)).unwrap();
        for id in ids {
            let (d, features, name) = (descriptor(id, 4), [id as u8 + 1; 3], format!("camera{id}"));
            let record = KeyframeRecord {
                local_features: (id != 1).then_some(&features[..]),
                frame_id: &name,
                tracker_pose: Some(pose),
                ..KeyframeRecord::new(id, stamp(id), &d)
            };
            store.append_keyframe(&record).unwrap();
        }
    }
    let report = merge(&a, &b, &out, 10).unwrap();
    assert_eq!(report, MergeReport { from_first: 3, from_second: 2, with_local_features: 3 });
    let merged = KeyframeStore::open_read_only(&out).unwrap();
    let features = merged.local_features(0).unwrap();
    assert_eq!(features, vec![(0, vec![1; 3]), (2, vec![3; 3]), (10, vec![1; 3])]);
    let frames = merged.frames(0).unwrap();
    let names: Vec<(u64, &str)> = frames.iter().map(|(id, (name, _))| (*id, name.as_str())).collect();
    assert_eq!(names, [(0, "camera0"), (1, "camera1"), (2, "camera2"), (10, "camera0"), (11, "camera1")]);
    assert!(frames.iter().all(|(_, (_, p))| *p == Some(pose)));
    // A store from before these tables existed merges with what it has.
    let old = dir.path().join("old.db");
    drop(store_with(&old, [20, 21], 4));
    rusqlite::Connection::open(&old).unwrap().execute_batch("DROP TABLE local_features; DROP TABLE frames;").unwrap();
    let report = merge(&a, &old, &dir.path().join("with_old.db"), 0).unwrap();
    assert_eq!(report, MergeReport { from_first: 3, from_second: 2, with_local_features: 2 });
}

/// Checks that `db` holds exactly the keyframes `ids` (in order) of `dim` values.
#[cfg(unix)]
fn assert_holds(db: &KeyframeDb, ids: &[u64], dim: usize) {
    assert_eq!(db.len(), ids.len());
    for (position, &id) in ids.iter().enumerate() {
        assert_eq!((db.id(position), db.stamp(position)), (id, stamp(id)), "position {position}");
        assert_eq!(db.descriptor(position), descriptor(id, dim).as_slice(), "position {position}");
    }
}

/// The vector file's inode: a rebuild replaces the file (by rename), so it changes.
#[cfg(unix)]
fn vector_file_inode(path: &Path) -> u64 {
    std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(vectors::path_for(path)).unwrap())
}

#[cfg(unix)]
fn vector_rows(path: &Path) -> u64 {
    VectorFile::open(&vectors::path_for(path)).unwrap().unwrap().header().unwrap().rows
}

/// Filling the vector file a few rows at a time (as `db merge` does, to bound its memory) writes the
/// same file as appending each row as it is stored.
#[cfg(unix)]
#[test]
fn the_vector_file_fills_in_steps() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    drop(store_with(&path, 0..9, 8));
    let appended = std::fs::read(vectors::path_for(&path)).unwrap();
    std::fs::remove_file(vectors::path_for(&path)).unwrap();
    KeyframeStore::open_existing(&path).unwrap().fill_vector_file(2).unwrap();
    assert_eq!(vector_rows(&path), 9);
    assert_eq!(std::fs::read(vectors::path_for(&path)).unwrap(), appended);
}

/// Rows stored behind the vector file's back (as by a crash between a commit and the append, or a
/// writer that does not know the file) are read from the database, and the file catches up.
#[cfg(unix)]
#[test]
fn a_load_maps_the_vector_file_and_catches_it_up() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("kf.db");
    let dim = 8;
    let empty = store_with(&path, [], dim);
    let inode = || vector_file_inode(&path);
    let created = inode();
    assert!(empty.load_db(None).unwrap().is_empty());
    assert_eq!(inode(), created, "an empty store's vector file was rebuilt");
    drop(empty);
    let store = store_with(&path, 0..20, dim);
    assert_eq!(vector_rows(&path), 20, "every append reaches the vector file");
    let db = store.load_db(None).unwrap();
    assert!(db.is_mapped());
    assert_holds(&db, &(0..20).collect::<Vec<_>>(), dim);
    for id in 20..25u64 {
        store
            .connection
            .execute(
                "INSERT INTO keyframes (id, stamp_nanos, descriptor) VALUES (?1, ?2, ?3)",
                params![id as i64, stamp(id).nanos, descriptor_blob(&descriptor(id, dim))],
            )
            .unwrap();
    }
    let mut store = KeyframeStore::open_existing(&path).unwrap();
    assert_eq!(vector_rows(&path), 20);
    let all: Vec<u64> = (0..25).collect();
    let db = store.load_db(None).unwrap();
    assert!(db.is_mapped());
    assert_holds(&db, &all, dim);
    assert_eq!(vector_rows(&path), 25, "the load appended the rows the file lacked");
    // The newest n, whether the file covers them or not.
    assert_holds(&store.load_db(Some(7)).unwrap(), &all[18..], dim);
    store.append(25, stamp(25), &descriptor(25, dim)).unwrap();
    assert_eq!(vector_rows(&path), 26);
    let mut db = store.load_db(Some(10)).unwrap();
    assert!(db.is_mapped());
    // A loaded history keeps growing and dropping like any other.
    for id in 26..40 {
        db.insert(id, stamp(id), &descriptor(id, dim)).unwrap();
    }
    db.drop_oldest(3);
    assert_holds(&db, &(19..40).collect::<Vec<_>>(), dim);
}

/// Keyframes stored with everything beside them (candidates, local features, a frame and pose, a
/// consistency state: rows in other tables, under the keyframe's id) reach the vector file in their
/// place: a load maps the file as written, without a rebuild, and holds every keyframe exactly. The
/// ids run apart from the row numbers, as a tracker's do.
#[cfg(unix)]
#[test]
fn keyframes_stored_with_side_records_keep_the_vector_file_in_step() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("side.db");
    let dim = 4;
    let mut store = store_with(&path, [], dim);
    let inode = || vector_file_inode(&path);
    let created = inode();
    let ids: Vec<u64> = (0..12).map(|i| 100 + 3 * i).collect();
    for (i, &id) in ids.iter().enumerate() {
        let d = descriptor(id, dim);
        let candidate = LoopCandidate {
            query_id: id,
            query_stamp: stamp(id),
            match_id: ids[0],
            match_stamp: stamp(ids[0]),
            distance: 0.5,
            score: 0.8,
            rank: 0,
            verified: None,
        };
        let candidates = if i % 2 == 1 { vec![candidate] } else { Vec::new() };
        store
            .append_keyframe(&KeyframeRecord {
                candidates: &candidates,
                local_features: Some(&[1, 2, 3]),
                frame_id: "camera",
                tracker_pose: Some(Isometry3::identity()),
                consistency: Some("{}"),
                ..KeyframeRecord::new(id, stamp(id), &d)
            })
            .unwrap();
        assert_eq!(vector_rows(&path), i as u64 + 1, "after keyframe {id}");
    }
    drop(store);
    let db = KeyframeStore::open_existing(&path).unwrap().load_db(None).unwrap();
    assert!(db.is_mapped());
    assert_holds(&db, &ids, dim);
    assert_eq!(inode(), created, "the vector file was rebuilt");
}

/// A vector file that is damaged, torn, from another database or not finite is rebuilt from the
/// database; the load's keyframes are exact either way, and the next load maps the rebuilt file.
#[cfg(unix)]
#[test]
fn a_damaged_or_foreign_vector_file_is_rebuilt() {
    let dir = tempfile::tempdir().unwrap();
    let dim = 8;
    let ids: Vec<u64> = (0..30).collect();
    let path = dir.path().join("kf.db");
    let vector_path = vectors::path_for(&path);
    drop(store_with(&path, ids.iter().copied(), dim));
    let other = dir.path().join("other.db");
    drop(store_with(&other, ids.iter().copied(), dim));
    let pristine = std::fs::read(&vector_path).unwrap();
    let value_at = |row: usize, value: usize| vectors::ROWS_OFFSET as usize + (row * dim + value) * 4;
    let nan_with_its_checksum = {
        let mut bytes = pristine.clone();
        bytes[value_at(29, 3)..value_at(29, 4)].copy_from_slice(&f32::NAN.to_le_bytes());
        let rows = &bytes[vectors::ROWS_OFFSET as usize..];
        let header = vectors::Header {
            crc: crc32fast::hash(rows),
            ..VectorFile::open(&vector_path).unwrap().unwrap().header().unwrap()
        };
        let file = VectorFile::create_empty(&dir.path().join("scratch"), dim, header.uid).unwrap();
        file.append_after(dim, &header.uid, None, header.last_seq, bytemuck::cast_slice(rows)).unwrap();
        std::fs::read(dir.path().join("scratch")).unwrap()
    };
    let damages: Vec<(&str, Vec<u8>)> = vec![
        ("a changed value", {
            let mut bytes = pristine.clone();
            bytes[value_at(11, 2)] ^= 1;
            bytes
        }),
        ("a torn end", pristine[..value_at(29, 5)].to_vec()),
        ("a damaged header", {
            let mut bytes = pristine.clone();
            bytes[60] ^= 1;
            bytes
        }),
        ("another database's file", std::fs::read(vectors::path_for(&other)).unwrap()),
        ("a value that is not finite", nan_with_its_checksum),
        ("not a vector file", b"hello".to_vec()),
    ];
    for (damage, bytes) in damages {
        std::fs::write(&vector_path, &bytes).unwrap();
        let store = KeyframeStore::open_existing(&path).unwrap();
        let db = store.load_db(None).unwrap();
        assert!(!db.is_mapped(), "{damage}: the damaged file was used");
        assert_holds(&db, &ids, dim);
        assert!(std::fs::read(&vector_path).unwrap() == pristine, "{damage}: not rebuilt as it was");
        assert!(store.load_db(None).unwrap().is_mapped(), "{damage}: the rebuilt file was not used");
    }
    // A missing file is written by the first load.
    std::fs::remove_file(&vector_path).unwrap();
    let store = KeyframeStore::open_existing(&path).unwrap();
    assert_holds(&store.load_db(None).unwrap(), &ids, dim);
    assert!(std::fs::read(&vector_path).unwrap() == pristine, "a missing vector file was not written as it was");
}

#[test]
fn candidates_are_stored_with_their_keyframe_and_read_back_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.db");
    let mut store = store_with(&path, [0, 1], 4);
    let candidate = |query: u64, matched: u64| LoopCandidate {
        query_id: query,
        query_stamp: stamp(query),
        match_id: matched,
        match_stamp: stamp(matched),
        distance: 0.25,
        score: 0.9,
        rank: 0,
        verified: None,
    };
    let with = |store: &mut KeyframeStore, id: u64, candidates: &[LoopCandidate]| {
        let d = descriptor(id, 4);
        store.append_keyframe(&KeyframeRecord { candidates, ..KeyframeRecord::new(id, stamp(id), &d) })
    };
    with(&mut store, 5, &[candidate(5, 0), candidate(5, 1)]).unwrap();
    with(&mut store, 3, &[candidate(3, 1)]).unwrap();
    // Insertion order (5 before 3), not id order; keyframes without candidates add nothing.
    let stored = store.stored_candidates().unwrap().unwrap();
    assert_eq!(stored.iter().map(|c| (c.query_id, c.match_id)).collect::<Vec<_>>(), [(5, 0), (5, 1), (3, 1)]);
    assert_eq!(stored[0], candidate(5, 0));
    // A refused keyframe stores neither it nor its candidates.
    assert!(with(&mut store, 5, &[candidate(5, 1)]).is_err());
    assert_eq!(store.stored_candidates().unwrap().unwrap().len(), 3);
    assert!(store.contains(3).unwrap() && !store.contains(4).unwrap());
    drop(store);
    // Read-only opens read them too; a merge holds only some candidates, so it says so.
    assert_eq!(KeyframeStore::open_read_only(&path).unwrap().stored_candidates().unwrap().unwrap().len(), 3);
    let other = dir.path().join("o.db");
    drop(store_with(&other, [10], 4));
    let merged = dir.path().join("m.db");
    merge(&path, &other, &merged, 0).unwrap();
    assert!(KeyframeStore::open_read_only(&merged).unwrap().stored_candidates().unwrap().is_none());
}

#[test]
fn local_features_are_stored_with_their_keyframe_updated_and_read_newest_first_limited() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f.db");
    let mut store = store_with(&path, [0], 4);
    let with_features = |store: &mut KeyframeStore, id: u64, features: &[u8]| {
        let d = descriptor(id, 4);
        store.append_keyframe(&KeyframeRecord {
            local_features: Some(features),
            ..KeyframeRecord::new(id, stamp(id), &d)
        })
    };
    for id in [1u64, 2, 3] {
        with_features(&mut store, id, &[id as u8; 3]).unwrap();
    }
    // Keyframe 0 has none; the newest two come oldest first.
    assert_eq!(store.local_features(0).unwrap(), vec![(1, vec![1; 3]), (2, vec![2; 3]), (3, vec![3; 3])]);
    assert_eq!(store.local_features(2).unwrap(), vec![(2, vec![2; 3]), (3, vec![3; 3])]);
    store.update_local_features(2, &[9, 9]).unwrap();
    let err = store.update_local_features(0, &[1]).unwrap_err().to_string();
    assert!(err.contains("keyframe 0 has no stored local features"), "{err}");
    // A duplicate id stores nothing: the keyframe's transaction is refused whole.
    assert!(with_features(&mut store, 3, &[7]).is_err());
    drop(store);
    let reopened = KeyframeStore::open_read_only(&path).unwrap();
    assert_eq!(reopened.local_features(0).unwrap(), vec![(1, vec![1; 3]), (2, vec![9, 9]), (3, vec![3; 3])]);
}

/// Only the newest keyframe's consistency state is kept, replaced in each keyframe's transaction; a
/// keyframe without one leaves the older one (which then belongs to an older keyframe).
#[test]
fn the_newest_consistency_state_is_kept_with_its_keyframe() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.db");
    let mut store = store_with(&path, [0], 4);
    assert_eq!(store.consistency().unwrap(), None);
    let with_state = |store: &mut KeyframeStore, id: u64, state: Option<&str>| {
        let d = descriptor(id, 4);
        store.append_keyframe(&KeyframeRecord { consistency: state, ..KeyframeRecord::new(id, stamp(id), &d) })
    };
    with_state(&mut store, 1, Some("one")).unwrap();
    with_state(&mut store, 2, Some("two")).unwrap();
    assert_eq!(store.consistency().unwrap(), Some((2, "two".to_string())));
    // A refused keyframe changes nothing.
    assert!(with_state(&mut store, 2, Some("again")).is_err());
    with_state(&mut store, 3, None).unwrap();
    drop(store);
    let reopened = KeyframeStore::open_existing(&path).unwrap();
    assert_eq!(reopened.consistency().unwrap(), Some((2, "two".to_string())));
    // The newest keyframes, oldest first, as many as there are.
    let ids = |count: usize| reopened.last_keyframes(count).unwrap().iter().map(|k| k.0).collect::<Vec<_>>();
    assert_eq!((ids(0), ids(2), ids(9)), (vec![], vec![2, 3], vec![0, 1, 2, 3]));
    assert_eq!(reopened.last_keyframes(1).unwrap()[0].2, descriptor(3, 4));
}

#[test]
fn frames_and_tracker_poses_are_stored_with_their_keyframe() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.db");
    let mut store = store_with(&path, [0], 4);
    let pose = Isometry3::from_parts(
        nalgebra::Translation3::new(1.5, -2.0, 0.25),
        nalgebra::UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
    );
    let d = descriptor(1, 4);
    store
        .append_keyframe(&KeyframeRecord {
            frame_id: "cam",
            tracker_pose: Some(pose),
            ..KeyframeRecord::new(1, stamp(1), &d)
        })
        .unwrap();
    let d = descriptor(2, 4);
    store.append_keyframe(&KeyframeRecord { frame_id: "cam", ..KeyframeRecord::new(2, stamp(2), &d) }).unwrap();
    drop(store);
    let frames = KeyframeStore::open_read_only(&path).unwrap().frames(0).unwrap();
    assert_eq!(frames.len(), 2, "keyframe 0 has neither");
    assert_eq!((frames[0].0, frames[0].1 .0.as_str(), frames[1].0, frames[1].1 .1), (1, "cam", 2, None));
    let back = frames[0].1 .1.unwrap();
    assert!((back.translation.vector - pose.translation.vector).norm() < 1e-15);
    assert!(back.rotation.angle_to(&pose.rotation) < 1e-12);
}
