//! `open_source` on the shared TUM sequences and on bad inputs: each bad input must give an
//! error that names the file and what is wrong, never a panic.

mod support;

use ecm_lcd::io::image_msg::WireEncoding;
use ecm_lcd::io::open_source;
use ecm_lcd::io::ros1bag::{write_ros1_bag, Ros1Compression};
use ecm_lcd::io::ros2bag::{write_ros2_bag, Ros2Storage};
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::types::{Frame, Stamp};
use image::RgbImage;
use std::fs;

fn rgb_txt_stamps(path: &std::path::Path) -> Vec<Stamp> {
    fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| Stamp::parse_secs(l.split_whitespace().next().unwrap()).unwrap())
        .collect()
}

#[test]
fn shared_tum_sequences_read_with_exact_stamps() {
    let tum = support::shared_dir().join("data/tum");
    for (name, count) in [("fr3_long_office_household", 17), ("fr2_desk", 20)] {
        let dir = tum.join(name);
        let source = open_source(&dir, None).unwrap();
        assert_eq!(source.len_hint(), Some(count));
        assert!(source.describe().starts_with("TUM folder"), "{}", source.describe());
        let frames: Vec<Frame> = source.map(|f| f.unwrap()).collect();
        assert_eq!(frames.len(), count);
        assert_eq!(frames.iter().map(|f| f.stamp).collect::<Vec<_>>(), rgb_txt_stamps(&dir.join("rgb.txt")));
        assert!(frames.iter().enumerate().all(|(i, f)| f.index == i && f.image.dimensions() == (640, 480)));
    }
    assert_eq!(
        open_source(&tum.join("fr3_long_office_household"), None).unwrap().next().unwrap().unwrap().stamp,
        Stamp::from_sec_nsec(1341847980, 722_988_000)
    );
    let poses = read_groundtruth(&tum.join("fr3_long_office_household/groundtruth.txt")).unwrap();
    assert!(!poses.is_empty());
    assert_eq!(poses[0].0, Stamp::from_sec_nsec(1341847981, 20_000_000));
    assert!((poses[0].1.translation.vector.x - -0.6749).abs() < 1e-12);
}

fn frames(n: usize, size: u32) -> Vec<(Stamp, RgbImage)> {
    (0..n).map(|i| (Stamp::from_sec_nsec(100 + i as i64, 0), RgbImage::from_pixel(size, size, image::Rgb([i as u8; 3])))).collect()
}

fn error_of(path: &std::path::Path, topic: Option<&str>) -> String {
    format!("{:#}", open_source(path, topic).err().expect("open must fail"))
}

#[test]
fn unknown_topic_lists_the_image_topics() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("a.bag");
    write_ros1_bag(&bag, "/camera/rgb", frames(2, 4), WireEncoding::Rgb8, Ros1Compression::None).unwrap();
    let err = error_of(&bag, Some("/camera/depth"));
    assert!(err.contains("a.bag has no topic /camera/depth; image topics: /camera/rgb (sensor_msgs/Image, 2 messages)"), "{err}");
    for storage in [Ros2Storage::Sqlite3, Ros2Storage::Mcap] {
        let bag = dir.path().join(format!("{storage:?}"));
        write_ros2_bag(&bag, storage, "/cam", frames(3, 4), WireEncoding::Png).unwrap();
        let err = error_of(&bag, Some("/nope"));
        assert!(err.contains("no topic /nope; image topics: /cam (sensor_msgs/msg/CompressedImage, 3 messages)"), "{err}");
    }
}

#[test]
fn truncated_bags_replay_up_to_the_damage_then_report_it() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("full.bag");
    write_ros1_bag(&bag, "/cam", frames(6, 300), WireEncoding::Rgb8, Ros1Compression::Lz4).unwrap();
    let bytes = fs::read(&bag).unwrap();
    let cut = dir.path().join("cut.bag");
    fs::write(&cut, &bytes[..bytes.len() * 3 / 4]).unwrap();
    let results: Vec<anyhow::Result<Frame>> = open_source(&cut, None).unwrap().collect();
    let (last, good) = results.split_last().unwrap();
    assert!(!good.is_empty() && good.len() < 6, "{} frames before the damage", good.len());
    assert!(good.iter().enumerate().all(|(i, f)| f.as_ref().unwrap().stamp.sec() == 100 + i as i64));
    let err = format!("{:#}", last.as_ref().unwrap_err());
    assert!(err.contains("cut.bag") && err.contains("byte offset"), "{err}");
    assert!(err.contains(&format!("read {} messages before the damage", good.len())), "{err}");

    let mcap_dir = dir.path().join("m");
    write_ros2_bag(&mcap_dir, Ros2Storage::Mcap, "/cam", frames(6, 300), WireEncoding::Rgb8).unwrap();
    let mcap = mcap_dir.join("m_0.mcap");
    let bytes = fs::read(&mcap).unwrap();
    let cut = dir.path().join("cut.mcap");
    fs::write(&cut, &bytes[..bytes.len() * 3 / 4]).unwrap();
    let results: Vec<anyhow::Result<Frame>> = open_source(&cut, None).unwrap().collect();
    let (last, good) = results.split_last().unwrap();
    assert!(good.iter().all(|f| f.is_ok()));
    let err = format!("{:#}", last.as_ref().unwrap_err());
    assert!(err.contains("cut.mcap") && err.contains(&format!("read {} messages", good.len())), "{err}");
}

#[test]
fn encoding_mismatch_names_the_message() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("s");
    write_ros2_bag(&bag, Ros2Storage::Sqlite3, "/cam", frames(2, 8), WireEncoding::Jpeg { quality: 80 }).unwrap();
    // Relabel the JPEG payloads as PNG: the CDR stays valid, the pixels do not decode.
    let db = rusqlite::Connection::open(bag.join("s_0.db3")).unwrap();
    let mut payloads: Vec<(i64, Vec<u8>)> = db
        .prepare("SELECT id, data FROM messages")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap()
        .map(|r| r.unwrap())
        .collect();
    for (id, data) in &mut payloads {
        let at = data.windows(4).position(|w| w == b"jpeg").unwrap();
        data[at..at + 4].copy_from_slice(b"png\0");
        db.execute("UPDATE messages SET data = ?1 WHERE id = ?2", rusqlite::params![&*data, *id]).unwrap();
    }
    drop(db);
    let results: Vec<anyhow::Result<Frame>> = open_source(&bag, None).unwrap().collect();
    assert_eq!(results.len(), 1);
    let err = format!("{:#}", results[0].as_ref().unwrap_err());
    assert!(err.contains("s_0.db3") && err.contains("message 0") && err.contains("do not decode as Png"), "{err}");
}

#[test]
fn missing_files_and_unknown_kinds_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let err = error_of(&dir.path().join("nothing.bag"), None);
    assert!(err.contains("nothing.bag does not exist"), "{err}");
    let other = dir.path().join("x.txt");
    fs::write(&other, "hello").unwrap();
    assert!(error_of(&other, None).contains("x.txt: unsupported source"));
    let err = error_of(dir.path(), None);
    assert!(err.contains("no rgb.txt and no png/jpg/jpeg/bmp images"), "{err}");
    fs::write(dir.path().join("rgb.txt"), "# only comments\n").unwrap();
    assert!(error_of(dir.path(), None).contains("rgb.txt lists no images"));
    fs::write(dir.path().join("rgb.txt"), "1.5 rgb/1.5.png\n").unwrap();
    let err = error_of(dir.path(), None);
    assert!(err.contains("rgb.txt:1: image file") && err.contains("rgb/1.5.png does not exist"), "{err}");
    let garbage = dir.path().join("g.bag");
    fs::write(&garbage, b"#ROSBAG V2.0\n\xff\xff\xff\xff").unwrap();
    let err = error_of(&garbage, None);
    assert!(err.contains("g.bag") && err.contains("byte offset 13"), "{err}");
    let mcap = dir.path().join("g.mcap");
    fs::write(&mcap, b"garbage").unwrap();
    assert!(error_of(&mcap, None).contains("g.mcap"));
    let bagdir = dir.path().join("bagdir");
    fs::create_dir(&bagdir).unwrap();
    fs::write(bagdir.join("metadata.yaml"), "x: 1").unwrap();
    assert!(error_of(&bagdir, None).contains("has metadata.yaml but no .db3 or .mcap file"));
}
