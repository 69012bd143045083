//! Loop candidates as CSV: the replay's output, written incrementally, and read back (by the
//! pose-graph back end and tools). A replay's file is first replaced by rename (with what the keyframe
//! database already holds, or just the header), then appended to and flushed keyframe by keyframe, so
//! what a killed replay emitted is on disk.

use std::fs::File;
use std::io::Write;
use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use nalgebra::{Matrix6, Quaternion, UnitQuaternion, Vector3};

use crate::types::{LoopCandidate, RelativePose, Stamp, Verified};

/// The columns of a match ([`columns`]).
const MATCH_HEADER: [&str; 6] = ["query_id", "query_stamp", "match_id", "match_stamp", "distance", "score"];

/// The columns of geometric verification before the covariance's ([`verification_columns`]).
const POSE_HEADER: [&str; 9] = ["inliers", "qx", "qy", "qz", "qw", "tx", "ty", "tz", "metric"];

/// Every column's name, in order ([`CandidateCsv`]).
pub fn columns() -> Vec<String> {
    MATCH_HEADER.iter().map(|name| name.to_string()).chain(verification_columns()).collect()
}

/// The columns of geometric verification: `inliers`, the relative pose, `metric` and the covariance
/// ([`CandidateCsv`]; [`verification_fields`]).
pub fn verification_columns() -> impl Iterator<Item = String> {
    POSE_HEADER.iter().map(|name| name.to_string()).chain(covariance_columns().map(|(name, _, _)| name))
}

/// The pose parameters in the order of ROS's `PoseWithCovariance` (translation, then rotation about
/// the x, y and z axes), which name the covariance columns.
const POSE_PARAMETERS: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];

/// The covariance columns: the upper triangle of the 6x6 matrix, row by row (`cov_x_x`, `cov_x_y`,
/// ..., `cov_rz_rz`), with each entry's row and column.
fn covariance_columns() -> impl Iterator<Item = (String, usize, usize)> {
    (0..6).flat_map(|row| {
        (row..6).map(move |column| (format!("cov_{}_{}", POSE_PARAMETERS[row], POSE_PARAMETERS[column]), row, column))
    })
}

/// Candidates as CSV (`query_id,query_stamp,match_id,match_stamp,distance,score`, then geometric
/// verification's `inliers` and the relative pose `qx,qy,qz,qw,tx,ty,tz` of the query camera in the
/// match camera's frame; empty where not verified or without intrinsics), `metric`: 1 where the
/// translation is in metres (the match keyframe had depth), 0 where it is a unit direction, and the
/// metric pose's covariance as the 21 columns of its upper triangle (`cov_x_x` ... `cov_rz_rz`, metres
/// and radians; empty where there is none). Written in pieces, each flushed.
pub struct CandidateCsv {
    out: csv::Writer<Box<dyn Write + Send>>,
    name: String,
}

impl CandidateCsv {
    /// A new file at `path` (replacing one there), or, with `append` and a non-empty file there, its
    /// continuation (no second header).
    pub fn to_file(path: &Path, append: bool) -> Result<Self> {
        crate::io::output::create_folder_of(path)?;
        let continuing = append && std::fs::metadata(path).is_ok_and(|m| m.len() > 0);
        if continuing {
            // Lines of these columns under another header would be misread.
            let mut found = String::new();
            std::io::BufRead::read_line(
                &mut std::io::BufReader::new(
                    File::open(path).with_context(|| format!("cannot read {}", path.display()))?,
                ),
                &mut found,
            )
            .with_context(|| format!("cannot read {}", path.display()))?;
            let found = found.trim_end();
            ensure!(
                found == columns().join(","),
                "{} has other columns than this version writes ({}); give another output file or remove it",
                path.display(),
                crate::io::excerpt(found, 60)
            );
        }
        let file = if continuing { File::options().append(true).open(path) } else { File::create(path) }
            .with_context(|| format!("cannot write {}", path.display()))?;
        Self::new(Box::new(file), path.display().to_string(), !continuing)
    }

    /// The file at `path` holding exactly `candidates`, open for appending after them. A regular file
    /// or a missing path is written beside and renamed over ([`crate::io::output::replace_with`]), so
    /// a crash leaves the old file or the new one; anything else (a device, a FIFO) is written in place.
    pub fn rewrite(path: &Path, candidates: &[LoopCandidate]) -> Result<Self> {
        let regular_or_missing = std::fs::symlink_metadata(path).map_or(true, |m| m.is_file());
        if !regular_or_missing {
            let mut csv = Self::to_file(path, false)?;
            csv.write(candidates)?;
            return Ok(csv);
        }
        crate::io::output::replace_with(path, |out| {
            let mut csv = csv::WriterBuilder::new().has_headers(false).from_writer(out);
            csv.write_record(columns())?;
            for c in candidates {
                csv.write_record(fields(c))?;
            }
            Ok(csv.flush()?)
        })?;
        Self::to_file(path, true)
    }

    pub fn to_stdout() -> Result<Self> {
        Self::new(Box::new(std::io::stdout()), "standard output".into(), true)
    }

    fn new(out: Box<dyn Write + Send>, name: String, header: bool) -> Result<Self> {
        let mut csv = CandidateCsv { out: csv::WriterBuilder::new().has_headers(false).from_writer(out), name };
        if header {
            csv.out.write_record(columns())?;
            csv.flush()?;
        }
        Ok(csv)
    }

    fn flush(&mut self) -> Result<()> {
        self.out.flush().with_context(|| format!("cannot write {}", self.name))
    }

    /// Writes `candidates` and flushes.
    pub fn write(&mut self, candidates: &[LoopCandidate]) -> Result<()> {
        for c in candidates {
            self.out.write_record(fields(c))?;
        }
        self.flush()
    }
}

/// One candidate's CSV fields, under [`columns`] ([`CandidateCsv`]).
pub fn fields(c: &LoopCandidate) -> Vec<String> {
    let mut record = vec![
        c.query_id.to_string(),
        c.query_stamp.to_string(),
        c.match_id.to_string(),
        c.match_stamp.to_string(),
        format!("{:.6}", c.distance),
        format!("{:.6}", c.score),
    ];
    record.extend(verification_fields(c.verified));
    record
}

/// A verification's fields under [`verification_columns`], all empty where there is none (and the
/// pose's where it has no pose, the covariance's where it has none).
pub fn verification_fields(verified: Option<Verified>) -> Vec<String> {
    let mut record = vec![verified.map(|v| v.inliers.to_string()).unwrap_or_default()];
    let pose = verified.and_then(|v| v.pose);
    let values = pose.map(|p| {
        let (q, t) = (p.rotation, p.translation);
        [q.i, q.j, q.k, q.w, t.x, t.y, t.z]
    });
    record.extend((0..7).map(|i| values.map(|values| format!("{:.6}", values[i])).unwrap_or_default()));
    record.push(pose.map(|p| u8::from(p.metric).to_string()).unwrap_or_default());
    let covariance = pose.and_then(|p| p.covariance);
    record.extend(
        covariance_columns().map(|(_, row, column)| {
            covariance.map(|matrix| format!("{:.6e}", matrix[(row, column)])).unwrap_or_default()
        }),
    );
    record
}

/// Writes candidates as a new CSV file ([`CandidateCsv::rewrite`]).
pub fn write_candidates_csv(candidates: &[LoopCandidate], path: &Path) -> Result<()> {
    CandidateCsv::rewrite(path, candidates).map(drop)
}

/// Reads a candidates CSV written by [`CandidateCsv`] (columns found by name; files from before the
/// `metric` column read as up to scale, from before the covariance columns without covariance). The
/// rank is the order of a query's lines.
pub fn read_candidates_csv(path: &Path) -> Result<Vec<LoopCandidate>> {
    let text = crate::io::read_capped_text(path, crate::io::limits::TEXT_LIST, "candidates CSV")?;
    // Comment lines (`#`, as in TUM files) are read as blank lines, which the reader skips but counts.
    let text: Vec<&str> = text.lines().map(|l| if l.trim_start().starts_with('#') { "" } else { l }).collect();
    let text = text.join("\n");
    // Spaces around fields (`a, b`, as a spreadsheet or a hand edit writes them) are not part of them.
    let mut reader = csv::ReaderBuilder::new().has_headers(true).trim(csv::Trim::All).from_reader(text.as_bytes());
    let header = reader.headers().with_context(|| format!("{}: no header line", path.display()))?.clone();
    let column = |name: &str| header.iter().position(|h| h == name);
    let required = |name: &str| {
        column(name).with_context(|| format!("{}: no `{name}` column (not a candidates CSV?)", path.display()))
    };
    let [query_id, query_stamp, match_id, match_stamp, distance, score] =
        ["query_id", "query_stamp", "match_id", "match_stamp", "distance", "score"].map(required);
    let (query_id, query_stamp, match_id, match_stamp, distance, score) =
        (query_id?, query_stamp?, match_id?, match_stamp?, distance?, score?);
    // A group of columns is there in whole or not at all (a file from before it): one column of it
    // missing would drop every relative pose without a word.
    let whole_group = |names: &[String], what: &str| -> Result<Option<Vec<usize>>> {
        let found: Vec<Option<usize>> = names.iter().map(|n| column(n)).collect();
        if found.iter().all(Option::is_none) {
            return Ok(None);
        }
        let missing: Vec<&str> =
            names.iter().zip(&found).filter(|(_, f)| f.is_none()).map(|(n, _)| n.as_str()).collect();
        ensure!(missing.is_empty(), "{}: the {what} columns lack `{}`", path.display(), missing.join("`, `"));
        Ok(Some(found.into_iter().flatten().collect()))
    };
    let pose_names = ["inliers", "qx", "qy", "qz", "qw", "tx", "ty", "tz"].map(str::to_string);
    let pose_columns = whole_group(&pose_names, "relative pose")?;
    let metric = column("metric");
    let covariance_names: Vec<String> = covariance_columns().map(|(name, _, _)| name).collect();
    let covariance_columns: Option<Vec<(usize, usize, usize)>> = whole_group(&covariance_names, "covariance")?
        .map(|found| found.into_iter().zip(covariance_columns()).map(|(i, (_, row, col))| (i, row, col)).collect());
    let mut candidates: Vec<LoopCandidate> = Vec::new();
    // The file's own line numbers: the reader skips empty lines (and the comments, blanked), and its
    // own count of lines does not hold across them. A record is one line in these files (no quoted
    // field holds a line break: every column is a number).
    let content_lines: Vec<usize> =
        text.lines().enumerate().filter(|(_, l)| !l.is_empty()).map(|(i, _)| i + 1).collect();
    for (row, record) in reader.records().enumerate() {
        let line = content_lines.get(row + 1).copied().unwrap_or(0);
        let record = record.map_err(|e| anyhow::anyhow!("{}:{line}: malformed CSV line: {e}", path.display()))?;
        let field = |i: usize| record.get(i).unwrap_or("");
        let number = |i: usize| -> Result<f64> {
            field(i).parse::<f64>().ok().filter(|v| v.is_finite()).with_context(|| {
                format!("{}:{line}: `{}` is not a finite number", path.display(), crate::io::excerpt(field(i), 40))
            })
        };
        let stamp = |i: usize| -> Result<Stamp> {
            Stamp::parse_secs(field(i))
                .with_context(|| format!("{}:{line}: bad stamp `{}`", path.display(), crate::io::excerpt(field(i), 40)))
        };
        let id = |i: usize| -> Result<u64> {
            field(i).parse::<u64>().with_context(|| {
                format!("{}:{line}: bad keyframe id `{}`", path.display(), crate::io::excerpt(field(i), 40))
            })
        };
        let verified = match &pose_columns {
            Some(cols) if !field(cols[0]).is_empty() => {
                let inliers = field(cols[0])
                    .parse::<u32>()
                    .with_context(|| format!("{}:{line}: bad inlier count", path.display()))?;
                let pose = if field(cols[1]).is_empty() {
                    None
                } else {
                    let v: Vec<f64> = cols[1..].iter().map(|&i| number(i)).collect::<Result<_>>()?;
                    let q = Quaternion::new(v[3], v[0], v[1], v[2]);
                    ensure!(
                        q.norm() > 0.5,
                        "{}:{line}: the rotation quaternion is not a unit quaternion",
                        path.display()
                    );
                    let metric = match metric.map(field) {
                        None | Some("") | Some("0") => false,
                        Some("1") => true,
                        Some(other) => bail!(
                            "{}:{line}: `metric` must be 0 or 1, found {}",
                            path.display(),
                            crate::io::excerpt(other, 20)
                        ),
                    };
                    let covariance = match &covariance_columns {
                        Some(columns) if !field(columns[0].0).is_empty() => {
                            let mut matrix = Matrix6::zeros();
                            for &(i, row, col) in columns {
                                matrix[(row, col)] = number(i)?;
                                matrix[(col, row)] = matrix[(row, col)];
                            }
                            Some(matrix)
                        }
                        _ => None,
                    };
                    Some(RelativePose {
                        rotation: UnitQuaternion::from_quaternion(q),
                        translation: Vector3::new(v[4], v[5], v[6]),
                        metric,
                        covariance,
                    })
                };
                Some(Verified { inliers, pose })
            }
            _ => None,
        };
        let query = id(query_id)?;
        let rank = candidates.iter().rev().take_while(|c| c.query_id == query).count() as u32;
        candidates.push(LoopCandidate {
            query_id: query,
            query_stamp: stamp(query_stamp)?,
            match_id: id(match_id)?,
            match_stamp: stamp(match_stamp)?,
            distance: number(distance)? as f32,
            score: number(score)? as f32,
            rank,
            verified,
        });
    }
    Ok(candidates)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_read_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.csv");
        // A covariance with correlations, of a pose with centimetre and milliradian errors.
        let spread =
            Matrix6::from_fn(|r, c| 1e-4 * (1.0 + r as f64) * (1.0 + c as f64) * if r < 3 { 1.0 } else { 0.1 });
        let covariance = spread * spread.transpose() + Matrix6::identity() * 1e-6;
        let pose = RelativePose {
            rotation: UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
            translation: Vector3::new(0.5, -0.25, 1.0),
            metric: true,
            covariance: Some(covariance),
        };
        let candidate = |query: u64, matched: u64, verified: Option<Verified>, rank: u32| LoopCandidate {
            query_id: query,
            query_stamp: Stamp::from_nanos(1_000_000_000 * query as i64 + 5),
            match_id: matched,
            match_stamp: Stamp::from_nanos(1_000_000_000 * matched as i64),
            distance: 0.25,
            score: 0.96875,
            rank,
            verified,
        };
        let written = vec![
            candidate(9, 1, None, 0),
            candidate(9, 2, Some(Verified { inliers: 40, pose: None }), 1),
            candidate(12, 3, Some(Verified { inliers: 55, pose: Some(pose) }), 0),
            candidate(
                13,
                4,
                Some(Verified { inliers: 20, pose: Some(RelativePose { metric: false, covariance: None, ..pose }) }),
                0,
            ),
        ];
        write_candidates_csv(&written, &path).unwrap();
        let read = read_candidates_csv(&path).unwrap();
        assert_eq!(read.len(), written.len());
        for (r, w) in read.iter().zip(&written) {
            assert_eq!(
                (r.query_id, r.match_id, r.query_stamp, r.match_stamp, r.rank),
                (w.query_id, w.match_id, w.query_stamp, w.match_stamp, w.rank)
            );
            assert_eq!(r.verified.map(|v| v.inliers), w.verified.map(|v| v.inliers));
            match (r.verified.and_then(|v| v.pose), w.verified.and_then(|v| v.pose)) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    assert_eq!(a.metric, b.metric);
                    match (a.covariance, b.covariance) {
                        (None, None) => {}
                        (Some(x), Some(y)) => assert!((x - y).amax() < 1e-6 * y.amax(), "{x} read, {y} written"),
                        other => panic!("covariance mismatch {other:?}"),
                    }
                    assert!(a.rotation.angle_to(&b.rotation) < 1e-5 && (a.translation - b.translation).norm() < 1e-5);
                }
                other => panic!("pose mismatch {other:?}"),
            }
        }
        // Appending to a file of other columns is refused, naming it.
        std::fs::write(&path, "query_id,query_stamp,match_id,match_stamp,distance,score\n").unwrap();
        let err = CandidateCsv::to_file(&path, true).err().expect("other columns refused").to_string();
        assert!(err.contains("c.csv has other columns"), "{err}");
        std::fs::write(&path, "query_id,stamp\n1,2\n").unwrap();
        let err = format!("{:#}", read_candidates_csv(&path).unwrap_err());
        assert!(err.contains("query_stamp") && err.contains("c.csv"), "{err}");
        // A pose that is not a number is refused, not passed on to a pose graph.
        let line = "1,2.0,0,1.0,0.5,0.9,30,0,0,0,1,NaN,0,1,0";
        std::fs::write(&path, format!("{},{}\n{line}\n", MATCH_HEADER.join(","), POSE_HEADER.join(","))).unwrap();
        let err = format!("{:#}", read_candidates_csv(&path).unwrap_err());
        assert!(err.contains("c.csv:2: `\"NaN\"` is not a finite number"), "{err}");
        // Errors name the file's own line, blank and comment lines counted.
        let header = format!("{},{}", MATCH_HEADER.join(","), POSE_HEADER.join(","));
        let good = "1,2.0,0,1.0,0.5,0.9,30,0,0,0,1,0,0,1,0";
        std::fs::write(&path, format!("{header}\n\n{good}\n# a note\n{line}\n")).unwrap();
        let err = format!("{:#}", read_candidates_csv(&path).unwrap_err());
        assert!(err.contains("c.csv:5: "), "{err}");
        std::fs::write(&path, format!("{header}\n\n{good}\n1,2\n")).unwrap();
        let err = format!("{:#}", read_candidates_csv(&path).unwrap_err());
        assert!(err.contains("c.csv:4: malformed"), "{err}");
        // Spaces after the commas are no part of the fields.
        std::fs::write(&path, format!("{}\n{}\n", header.replace(',', ", "), good.replace(',', ", "))).unwrap();
        let read = read_candidates_csv(&path).unwrap();
        assert_eq!(read[0].verified.map(|v| v.inliers), Some(30));
        // One pose column missing loses every pose: refused, naming it.
        let without_tz = |line: &str| {
            line.split(',').enumerate().filter(|(i, _)| *i != 13).map(|(_, f)| f).collect::<Vec<_>>().join(",")
        };
        std::fs::write(&path, format!("{}\n{}\n", without_tz(&header), without_tz(good))).unwrap();
        let err = format!("{:#}", read_candidates_csv(&path).unwrap_err());
        assert!(err.contains("c.csv: the relative pose columns lack `tz`"), "{err}");
    }
}
