//! `rgbid config`: configurations as data (print the defaults, check a file).

use anyhow::Result;
use rgbid::io::settings::to_toml;
use rgbid::mono::MonoConfig;
use rgbid::odometry::OdometryConfig;
use rgbid::place::LoopDetectorParams;
use rgbid::segment::SegmentConfig;
use rgbid::slam::SlamConfig;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::options::ConfigArgs;

/// Subcommands of `rgbid config`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Print a command's configuration as TOML: the defaults, or with --config / --set the
    /// result of applying them (a check of a file). The output is a valid --config file.
    Dump(DumpArgs),
}

/// Whose configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    /// `rgbid slam` and `rgbid demo` (`SlamConfig`).
    #[value(alias = "demo")]
    Slam,
    /// `rgbid odometry` and `rgbid bench odometry` (`OdometryConfig`).
    #[value(alias = "bench")]
    Odometry,
    /// `rgbid segment` (`SegmentConfig`).
    Segment,
    /// `rgbid place loops` (`LoopDetectorParams`).
    Place,
    /// `rgbid mono` (`MonoConfig`).
    Mono,
    /// `rgbid scale` (`DynScaleConfig`).
    Scale,
}

/// Arguments of `rgbid config dump`.
#[derive(clap::Args)]
pub struct DumpArgs {
    /// The command whose configuration is printed.
    #[arg(long, value_enum, default_value_t = Target::Slam)]
    pub command: Target,
    /// Print JSON instead of TOML.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub config: ConfigArgs,
}

/// Runs `rgbid config`.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Dump(a) => {
            let text = match a.command {
                Target::Slam => dump(SlamConfig::default(), &a)?,
                Target::Odometry => dump(OdometryConfig::default(), &a)?,
                Target::Segment => dump(SegmentConfig::default(), &a)?,
                Target::Place => dump(LoopDetectorParams::default(), &a)?,
                Target::Mono => dump(MonoConfig::default(), &a)?,
                Target::Scale => dump(super::scale::defaults(), &a)?,
            };
            print!("{text}");
            Ok(())
        }
    }
}

/// `base` with the file and assignments of `a` applied, as TOML or JSON text.
fn dump<T: Serialize + DeserializeOwned>(base: T, a: &DumpArgs) -> Result<String> {
    let config = a.config.resolve(base, |_| Ok(()))?;
    Ok(if a.json {
        serde_json::to_string_pretty(&config)? + "\n"
    } else {
        to_toml(&config)?
    })
}
