//! Prints what a data set holds and writes a contact sheet (first, middle and last frame of
//! every view, smoke box in red).
//!
//! `cargo run --release -p gausmoke-data --example inspect -- DATASET OUT.png [WIDTH HEIGHT]`
//! where DATASET is a PINF folder (with `info.json`) or a D-NeRF folder
//! (with `transforms_train.json`).

use std::path::Path;
use std::process::ExitCode;

use gausmoke_data::{LoadOptions, inspect, load_dnerf, load_pinf};

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: inspect DATASET OUT.png [WIDTH HEIGHT]";
    let (Some(dataset), Some(out)) = (args.first(), args.get(1)) else {
        eprintln!("{usage}");
        return ExitCode::FAILURE;
    };
    let resolution = match (args.get(2), args.get(3)) {
        (Some(w), Some(h)) => match (w.parse(), h.parse()) {
            (Ok(w), Ok(h)) => Some((w, h)),
            _ => {
                eprintln!("WIDTH and HEIGHT must be integers; {usage}");
                return ExitCode::FAILURE;
            }
        },
        _ => None,
    };
    let options = LoadOptions {
        resolution,
        ..Default::default()
    };
    let path = Path::new(dataset);
    let loaded = if path.join("transforms_train.json").is_file() {
        load_dnerf(path, &options)
    } else {
        load_pinf(path, &options)
    };
    let ds = match loaded {
        Ok(ds) => ds,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
    };
    print!("{}", inspect::summary(&ds));
    let Some(sheet) = inspect::contact_sheet(&ds) else {
        eprintln!("no frames loaded");
        return ExitCode::FAILURE;
    };
    if let Err(e) = sheet.save_png(Path::new(out)) {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    println!("contact sheet: {out}");
    ExitCode::SUCCESS
}
