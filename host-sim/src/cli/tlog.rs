//! `harmonic-sim tlog`: summarise a MAVLink .tlog (the reading is `harmonic_sim::vehicle::tlog`).

use std::path::PathBuf;

use harmonic_sim::vehicle::tlog;

/// The flags of `tlog`.
#[derive(clap::Args)]
pub struct TlogArgs {
    /// The .tlog file (8-byte big-endian µs timestamp before each MAVLink frame).
    file: PathBuf,
    /// Component id whose messages count as sent ("out"): the companion computer's.
    #[arg(long, default_value_t = 191)]
    companion_component: u8,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// Run `tlog`: read the file and print its summary, as text or JSON.
pub fn run(args: &TlogArgs) -> Result<(), String> {
    let bytes = std::fs::read(&args.file).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let records = tlog::read_records(&bytes).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let summary = tlog::summarize(&records, args.companion_component);
    if args.json {
        println!("{}", serde_json::to_string(&summary).map_err(|e| e.to_string())?);
    } else {
        print!("{}", tlog::format_summary(&summary));
    }
    Ok(())
}
