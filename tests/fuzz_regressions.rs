//! The fuzz targets' code (tests/fuzz/targets.rs) over the seed corpus (tests/fuzz/corpus/<target>/)
//! and over every crash input fuzzing found (tests/fuzz/crashes/<target>/, kept once the crash was
//! fixed): each input must be handled without a panic. Runs in the normal test command; fuzzing
//! itself is `tests/fuzz/run.sh` (see the README, Reliability).

#[path = "fuzz/targets.rs"]
mod targets;

use std::path::Path;

fn inputs(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut files: Vec<_> = entries.map(|e| e.unwrap().path()).filter(|p| p.is_file()).collect();
    files.sort();
    files.into_iter().map(|p| (p.display().to_string(), std::fs::read(&p).unwrap())).collect()
}

#[test]
fn seed_corpus_and_fixed_crash_inputs_do_not_panic() {
    let fuzz = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz");
    let (mut seeds, mut crashes, mut panics) = (0, 0, Vec::new());
    for (name, target) in targets::TARGETS {
        let corpus = inputs(&fuzz.join("corpus").join(name));
        assert!(!corpus.is_empty(), "no seed corpus for fuzz target {name} in {}", fuzz.join("corpus").display());
        let found = inputs(&fuzz.join("crashes").join(name));
        seeds += corpus.len();
        crashes += found.len();
        for (file, bytes) in corpus.iter().chain(&found) {
            if std::panic::catch_unwind(|| target(bytes)).is_err() {
                panics.push(file.clone());
            }
        }
    }
    println!(
        "{seeds} seed inputs and {crashes} former crash inputs replayed through {} targets",
        targets::TARGETS.len()
    );
    assert!(panics.is_empty(), "inputs that panic: {panics:#?}");
}
