//! Bags written by an independent tool (`rosbags` from PyPI, in a test-only virtualenv) read by
//! our readers, and bags written by our writers read by `rosbags` and by our readers.
//! The pixel pattern mirrors `tests/support/rosbags_fixtures.py`.

mod support;

use ecm_lcd::io::image_msg::{encode_image, mono16_to_8, WireEncoding};
use ecm_lcd::io::ros1bag::{write_ros1_bag, Ros1Compression};
use ecm_lcd::io::ros2bag::{write_ros2_bag, Ros2Storage};
use ecm_lcd::io::{open_source, open_source_topics, Topics};
use ecm_lcd::types::{Frame, Stamp};
use image::{Rgb, RgbImage};
use sha2::{Digest, Sha256};
use std::path::Path;

const WIDTH: u32 = 16;
const HEIGHT: u32 = 12;
const FRAMES: usize = 5;

fn header_stamp(i: usize) -> Stamp {
    Stamp::from_sec_nsec(1341847980 + i as i64, 722988000 + i as u32 * 1001)
}

fn rgb_pattern(i: usize) -> RgbImage {
    let i = i as u32;
    RgbImage::from_fn(WIDTH, HEIGHT, |x, y| {
        Rgb([((x * 13 + i * 29) & 255) as u8, ((y * 17 + i * 7) & 255) as u8, ((x * y * 3 + i) & 255) as u8])
    })
}

fn grey(f: impl Fn(u32, u32) -> u8) -> RgbImage {
    RgbImage::from_fn(WIDTH, HEIGHT, |x, y| Rgb([f(x, y); 3]))
}

fn expected_image(topic: &str, i: usize) -> RgbImage {
    let n = i as u32;
    match topic {
        "mono8" => grey(|x, y| ((x * 9 + y * 14 + n * 5) & 255) as u8),
        "mono16_le" | "mono16_be" => grey(|x, y| mono16_to_8(((x * 2000 + y * 3000 + n * 111) & 0xFFFF) as u16)),
        _ => rgb_pattern(i),
    }
}

const TOPICS: [&str; 9] = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16_le", "mono16_be", "jpeg", "png"];

fn check_frames(source_name: &str, topic: &str, frames: &[Frame]) {
    assert_eq!(frames.len(), FRAMES, "{source_name} {topic}");
    for (i, frame) in frames.iter().enumerate() {
        assert_eq!(frame.index, i);
        assert_eq!(frame.stamp, header_stamp(i), "{source_name} {topic} frame {i}: header stamp, not receive time");
        let expected = expected_image(topic, i);
        if topic == "jpeg" {
            let diffs: Vec<u32> =
                frame.image.as_raw().iter().zip(expected.as_raw()).map(|(a, b)| a.abs_diff(*b) as u32).collect();
            let mean = diffs.iter().sum::<u32>() as f64 / diffs.len() as f64;
            assert!(mean < 3.0, "{source_name} jpeg frame {i}: mean abs diff {mean}");
        } else {
            assert_eq!(frame.image, expected, "{source_name} {topic} frame {i}");
        }
    }
}

#[test]
fn rosbags_written_bags_read_with_every_encoding() {
    let dir = tempfile::tempdir().unwrap();
    support::rosbags_fixtures(&["write".as_ref(), dir.path().as_os_str()]);
    for bag in ["ros1_none.bag", "ros1_bz2.bag", "ros1_lz4.bag", "ros2_sqlite3", "ros2_mcap"] {
        let path = dir.path().join(bag);
        for topic in TOPICS {
            let source = open_source(&path, Some(&format!("/{topic}"))).unwrap_or_else(|e| panic!("{bag}: {e:#}"));
            assert_eq!(source.len_hint(), Some(FRAMES), "{bag} {topic}");
            let frames: Vec<Frame> = source.map(|f| f.unwrap_or_else(|e| panic!("{bag} {topic}: {e:#}"))).collect();
            check_frames(bag, topic, &frames);
        }
        let err = open_source(&path, None).err().unwrap().to_string();
        assert!(err.contains("11 image topics") && err.contains("/mono16_be (sensor_msgs"), "{bag}: {err}");
        // The calibration beside the image topics (the fixture's CAMERA_K), raw or compressed.
        for topic in ["/rgb8", "/jpeg"] {
            let source = open_source(&path, Some(topic)).unwrap();
            let carried = source.intrinsics().unwrap_or_else(|| panic!("{bag} {topic}: no intrinsics"));
            let expected = ecm_lcd::verification::Intrinsics {
                fx: 525.25,
                fy: 526.5,
                cx: 7.75,
                cy: 5.5,
                size: Some([WIDTH, HEIGHT]),
            };
            assert_eq!(
                (carried.intrinsics, carried.origin.as_str()),
                (expected, "topic /camera_info"),
                "{bag} {topic}"
            );
        }
        check_depth_pairing(bag, &path);
    }
    // The storage file of a ROS 2 bag folder opens directly too.
    let db3 = dir.path().join("ros2_sqlite3/ros2_sqlite3.db3");
    let frames: Vec<Frame> = open_source(&db3, Some("/png")).unwrap().map(|f| f.unwrap()).collect();
    check_frames("db3 file", "png", &frames);
}

/// Frame `i`'s depth in metres, mirroring the fixture's `depth_mm_pattern` (0 where unknown).
fn expected_depth(i: usize) -> Vec<f32> {
    let mut metres = Vec::new();
    for y in 0..HEIGHT as usize {
        for x in 0..WIDTH as usize {
            let mm = 500 + x * 10 + y * 20 + i;
            metres.push(if (x, y) == (0, 0) { 0.0 } else { mm as f32 / 1000.0 });
        }
    }
    metres
}

/// Each bag's depth topics paired with a colour topic: every frame but the fixture's frame 3 gets
/// its own depth image (stamped 7 ms later), in metres from both encodings.
fn check_depth_pairing(bag: &str, path: &Path) {
    for depth_topic in ["/depth16", "/depth32"] {
        let topics = Topics { image: Some("/rgb8".into()), depth: Some(depth_topic.into()), poses: None };
        let source = open_source_topics(path, &topics).unwrap_or_else(|e| panic!("{bag}: {e:#}"));
        assert_eq!(source.len_hint(), Some(FRAMES), "{bag} {depth_topic}");
        assert!(source.describe().contains(&format!("depth {depth_topic} (4 messages)")), "{}", source.describe());
        let frames: Vec<Frame> = source.map(|f| f.unwrap_or_else(|e| panic!("{bag} {depth_topic}: {e:#}"))).collect();
        check_frames(bag, "rgb8", &frames);
        for (i, frame) in frames.iter().enumerate() {
            match (&frame.depth, i) {
                (None, 3) => {}
                (Some(depth), i) if i != 3 => {
                    assert_eq!((depth.width, depth.height), (WIDTH, HEIGHT));
                    let expected = expected_depth(i);
                    let worst = depth.metres.iter().zip(&expected).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
                    assert!(worst < 1e-6, "{bag} {depth_topic} frame {i}: depth off by {worst} m");
                }
                (depth, i) => panic!("{bag} {depth_topic} frame {i}: depth present {}", depth.is_some()),
            }
        }
    }
    let wrong = Topics { image: Some("/rgb8".into()), depth: Some("/jpeg".into()), poses: None };
    let err = open_source_topics(path, &wrong).err().unwrap().to_string();
    assert!(err.contains("depth topic /jpeg") && err.contains("not sensor_msgs Image"), "{bag}: {err}");
    let colour = Topics { image: Some("/rgb8".into()), depth: Some("/rgb8".into()), poses: None };
    let err = open_source_topics(path, &colour).err().unwrap().to_string();
    assert!(err.contains("is the colour topic"), "{bag}: {err}");
    // A colour topic as depth is refused by its encoding at the first message.
    let mono = Topics { image: Some("/rgb8".into()), depth: Some("/rgba8".into()), poses: None };
    let err = format!("{:#}", open_source_topics(path, &mono).unwrap().find_map(|f| f.err()).unwrap());
    assert!(err.contains("unsupported depth encoding \"rgba8\""), "{bag}: {err}");
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// What rosbags read from one message, as printed by the fixture script.
fn rosbags_read(bag: &Path, topic: &str) -> Vec<serde_json::Value> {
    support::rosbags_fixtures(&["read".as_ref(), bag.as_os_str(), topic.as_ref()])
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect()
}

#[test]
fn our_bags_read_by_rosbags_and_by_us() {
    let dir = tempfile::tempdir().unwrap();
    let frames: Vec<(Stamp, RgbImage)> = (0..3).map(|i| (header_stamp(i), rgb_pattern(i))).collect();
    let cases: [(&str, WireEncoding); 4] = [
        ("bgr8", WireEncoding::Bgr8),
        ("mono16_be", WireEncoding::Mono16 { big_endian: true }),
        ("jpeg", WireEncoding::Jpeg { quality: 90 }),
        ("png", WireEncoding::Png),
    ];
    let mut bags = Vec::new();
    for (i, compression) in [Ros1Compression::None, Ros1Compression::Bz2, Ros1Compression::Lz4].into_iter().enumerate()
    {
        let (name, encoding) = cases[i];
        let path = dir.path().join(format!("ours_{compression:?}.bag"));
        write_ros1_bag(&path, "/camera/image", frames.clone(), encoding, compression).unwrap();
        bags.push((path, name, encoding));
    }
    for (storage, (name, encoding)) in [(Ros2Storage::Sqlite3, cases[3]), (Ros2Storage::Mcap, cases[0])] {
        let path = dir.path().join(format!("ours_{storage:?}"));
        write_ros2_bag(&path, storage, "/camera/image", frames.clone(), encoding).unwrap();
        bags.push((path, name, encoding));
    }
    for (path, name, encoding) in bags {
        let seen = rosbags_read(&path, "/camera/image");
        assert_eq!(seen.len(), frames.len(), "{}", path.display());
        for (i, (line, (stamp, image))) in seen.iter().zip(&frames).enumerate() {
            let sent = encode_image(*stamp, "camera", image, encoding).unwrap();
            let (sent_data, sent_format) = match &sent {
                ecm_lcd::io::image_msg::ImageMessage::Raw(m) => (&m.data, m.encoding.clone()),
                ecm_lcd::io::image_msg::ImageMessage::Compressed(m) => (&m.data, m.format.clone()),
            };
            assert_eq!(line["sec"].as_i64(), Some(stamp.sec()), "{name} {i}");
            assert_eq!(line["nanosec"].as_u64(), Some(stamp.nsec() as u64), "{name} {i}");
            assert_eq!(line["receive_time"].as_i64(), Some(stamp.nanos), "{name} {i}");
            assert_eq!(line["sha256"].as_str(), Some(sha256_hex(sent_data).as_str()), "{name} {i}");
            let format = line.get("encoding").or_else(|| line.get("format")).and_then(|v| v.as_str());
            assert_eq!(format, Some(sent_format.as_str()), "{name} {i}");
        }
        let ours: Vec<Frame> = open_source(&path, None).unwrap().map(|f| f.unwrap()).collect();
        assert_eq!(ours.iter().map(|f| f.stamp).collect::<Vec<_>>(), frames.iter().map(|f| f.0).collect::<Vec<_>>());
        if name == "png" || name == "bgr8" {
            assert!(ours.iter().zip(&frames).all(|(a, b)| a.image == b.1), "{name}");
        }
    }
}

/// A synthetic sequence with depth, written by `rosbags` as a ROS 1 bag laid out like TUM's (rgb8
/// colour with its `camera_info`, 32FC1 depth on its own topic), replays through the binary like the
/// TUM folder it came from, given the same intrinsics as parameters: the same candidates, each verified
/// with a metric pose. The bag's intrinsics come from its `camera_info` alone. Without
/// `--depth-topic` the same bag gives poses up to scale only.
#[test]
fn a_tum_style_bag_with_depth_replays_like_its_folder() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let bag = dir.path().join("seq.bag");
    let arg = |p: &Path| p.to_str().unwrap().to_string();
    support::ecm_lcd_ok(&["synth", "-o", &arg(&seq), "--frames", "240", "--laps", "2", "--rate", "5", "--depth"]);
    // The renderer's camera: focal 0.82 * width, principal point at the centre.
    let (fx, fy, cx, cy) = ("262.4", "262.4", "160", "120");
    let tum_bag = ["tum-bag", &arg(&seq), &arg(&bag), fx, fy, cx, cy];
    support::rosbags_fixtures(&tum_bag.map(std::ffi::OsStr::new));
    let replay = |source: &Path, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let mut args = vec!["replay".to_string(), arg(source), "-o".into(), arg(&out), "--quiet".into()];
        args.extend(extra.iter().map(|s| s.to_string()));
        support::ecm_lcd_ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
        ecm_lcd::io::candidates::read_candidates_csv(&out).unwrap()
    };
    let camera =
        [format!("camera.fx={fx}"), format!("camera.fy={fy}"), format!("camera.cx={cx}"), format!("camera.cy={cy}")];
    let camera: Vec<&str> = camera.iter().flat_map(|p| ["--param", p.as_str()]).collect();
    let from_folder = replay(&seq, &camera, "folder.csv");
    let from_bag =
        replay(&bag, &["--topic", "/camera/rgb/image_color", "--depth-topic", "/camera/depth/image"], "bag.csv");
    let without_depth = replay(&bag, &["--topic", "/camera/rgb/image_color"], "no_depth.csv");
    println!("{} candidates from the folder, {} from the bag", from_folder.len(), from_bag.len());
    assert!(from_folder.len() >= 10, "{} candidates from the folder", from_folder.len());
    let pairs = |c: &[ecm_lcd::types::LoopCandidate]| c.iter().map(|c| (c.query_id, c.match_id)).collect::<Vec<_>>();
    assert_eq!(pairs(&from_bag), pairs(&from_folder));
    assert_eq!(pairs(&without_depth), pairs(&from_folder));
    for ((bag, folder), plain) in from_bag.iter().zip(&from_folder).zip(&without_depth) {
        let (bag_pose, folder_pose) = (bag.verified.unwrap().pose.unwrap(), folder.verified.unwrap().pose.unwrap());
        assert!(bag_pose.metric && folder_pose.metric, "{} -> {}: metric from depth", bag.query_id, bag.match_id);
        let apart = (bag_pose.translation - folder_pose.translation).norm();
        assert!(apart < 1e-3, "{} -> {}: bag and folder poses {apart} m apart", bag.query_id, bag.match_id);
        assert!(!plain.verified.unwrap().pose.unwrap().metric, "no depth topic: pose up to scale");
    }

    // As a map for `match`: the first lap as a TUM folder with depth.txt, and the same lap as a bag
    // with `--depth-topic`, place the second lap's images alike, with the same metric poses.
    let (lap1, lap1_bag, lap2) = (dir.path().join("lap1"), dir.path().join("lap1.bag"), dir.path().join("lap2"));
    support::split_into_map_and_queries(&seq, &lap1, &lap2);
    support::rosbags_fixtures(&["tum-bag", &arg(&lap1), &arg(&lap1_bag), fx, fy, cx, cy].map(std::ffi::OsStr::new));
    let placed = |map: &Path, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let args = ["match", "--database", &arg(map), "--queries", &arg(&lap2), "-o", &arg(&out)];
        support::ecm_lcd_ok(&[&args[..], extra].concat());
        std::fs::read_to_string(out).unwrap()
    };
    let from_folder = placed(&lap1, &camera, "placed_folder.csv");
    let from_bag = placed(
        &lap1_bag,
        &["--topic", "/camera/rgb/image_color", "--depth-topic", "/camera/depth/image"],
        "placed_bag.csv",
    );
    let rows = |text: &str| -> Vec<Vec<String>> {
        text.lines().skip(1).map(|line| line.split(',').map(str::to_string).collect()).collect()
    };
    let (folder_rows, bag_rows) = (rows(&from_folder), rows(&from_bag));
    assert_eq!(folder_rows.len(), 120);
    let metric = folder_rows.iter().filter(|row| row[14] == "1").count();
    println!("{metric} of 120 second-lap frames placed on the first lap with metric poses");
    assert!(metric >= 100, "{metric} metric");
    for (folder_row, bag_row) in folder_rows.iter().zip(&bag_rows) {
        // Query, match, score, accepted, inliers and metric agree; the frames are named alike by stamp.
        for column in [0, 1, 2, 3, 4, 5, 6, 14] {
            assert_eq!(folder_row[column], bag_row[column], "column {column}:\n{folder_row:?}\n{bag_row:?}");
        }
        if folder_row[14] == "1" {
            let t = |row: &[String]| {
                nalgebra::Vector3::from_iterator(row[11..14].iter().map(|v| v.parse::<f64>().unwrap()))
            };
            assert!((t(folder_row) - t(bag_row)).norm() < 1e-3, "{folder_row:?}\n{bag_row:?}");
        }
    }
}
