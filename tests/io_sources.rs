//! `open_source` on the shared TUM sequences (bad inputs: see `malformed_inputs.rs`).

mod support;

use ecm_lcd::io::open_source;
use ecm_lcd::io::tum::read_groundtruth;
use ecm_lcd::types::{Frame, Stamp};
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
