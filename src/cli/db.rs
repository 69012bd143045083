//! `ecm-lcd db info|export|merge`: inspect, export and merge the persistent keyframe databases that
//! `replay --db` and `node --db` write ([`ecm_lcd::detector::store`]).

use std::path::PathBuf;

use anyhow::Result;

use ecm_lcd::detector::store::{self, decode_descriptor, KeyframeStore};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: DbCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum DbCommand {
    /// Count, id range, stamps, weights hash, arch, descriptor mode and size of a database.
    Info { path: PathBuf },
    /// Every keyframe as CSV: id, stamp, then the descriptor values d0, d1, ...
    Export {
        path: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
    },
    /// A new database with FIRST's keyframes then SECOND's (same weights, arch, mode and input size;
    /// ids kept, a clash of ids is an error unless --offset moves SECOND's ids).
    Merge {
        first: PathBuf,
        second: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
        /// Added to every id of SECOND.
        #[arg(long, default_value_t = 0)]
        offset: u64,
    },
}

pub fn run(args: Args) -> Result<()> {
    match args.command {
        DbCommand::Info { path } => {
            let store = KeyframeStore::open_read_only(&path)?;
            let summary = store.summary()?;
            let identity = store.identity();
            println!("database:        {}", path.display());
            println!("keyframes:       {}", summary.count);
            match summary.ids {
                Some((first, last)) => println!("ids:             {first} .. {last}"),
                None => println!("ids:             -"),
            }
            match summary.stamps {
                Some((first, last)) => {
                    println!("stamps:          {first} .. {last} ({:.3} s)", last.as_secs_f64() - first.as_secs_f64())
                }
                None => println!("stamps:          -"),
            }
            println!("weights sha256:  {}", identity.weights_sha256);
            println!("arch:            {}", identity.arch);
            println!("descriptor:      {} ({} values)", identity.descriptor_mode, identity.dim);
            println!("input size:      {}", identity.input_size);
            println!("size on disk:    {} bytes", summary.bytes);
            Ok(())
        }
        DbCommand::Export { path, output } => {
            ecm_lcd::io::output::ensure_not_an_input(&output, &[&path])?;
            ecm_lcd::io::output::ensure_writable_outputs(&[("-o", &output)])?;
            let store = KeyframeStore::open_read_only(&path)?;
            ecm_lcd::io::output::replace_with(&output, |file| {
                let mut out = csv::Writer::from_writer(file);
                let mut header = vec!["id".to_string(), "stamp".to_string()];
                header.extend((0..store.identity().dim).map(|i| format!("d{i}")));
                out.write_record(&header)?;
                let mut record = Vec::with_capacity(header.len());
                store.for_each(0, |id, stamp, blob| {
                    record.clear();
                    record.push(id.to_string());
                    record.push(stamp.to_string());
                    // Shortest text that reads back to the same f32.
                    record.extend(decode_descriptor(blob).map(|v| v.to_string()));
                    Ok(out.write_record(&record)?)
                })?;
                Ok(out.flush()?)
            })?;
            eprintln!("{} keyframes written to {}", store.len(), output.display());
            Ok(())
        }
        DbCommand::Merge { first, second, output, offset } => {
            // Not an input, nor a file beside one (`a.db-wal`); the output may name a new folder.
            ecm_lcd::io::output::ensure_not_an_input(&output, &[&first, &second])?;
            ecm_lcd::io::output::create_folder_of(&output)?;
            let report = store::merge(&first, &second, &output, offset)?;
            eprintln!(
                "{} keyframes from {} and {} from {} written to {} ({} with local features for verification)",
                report.from_first,
                first.display(),
                report.from_second,
                second.display(),
                output.display(),
                report.with_local_features
            );
            Ok(())
        }
    }
}
