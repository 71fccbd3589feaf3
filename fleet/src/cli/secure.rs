//! `fleet secure [mission] --out DIR [--tls CERTDIR]`: the Zenoh configs of a secured mission
//! (see `fleet_mission::security`): `router.json5` for the model server, `<user>.json5` for
//! each vehicle, the ground-station gateway and an observer, `credentials.txt` (the
//! router's password dictionary, fresh random passwords, mode 0600), and the MAVLink 2 signing
//! keys (`fleet_mission::signing_key`): `mavlink-signing.key` for the ground-station link and
//! `autopilot/<id>.key` for each vehicle's autopilot link, each with its `.passphrase` (what
//! MAVProxy and QGroundControl take), mode 0600.

use anyhow::Context;
use fleet_mission::config::MissionConfig;
use fleet_mission::security::{client_config, router_config, users, Tls};
use fleet_mission::signing_key::{write_private, SigningKey};
use std::io::Read;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The mission file (default: the bundled mission).
    pub mission: Option<PathBuf>,
    /// Where to write the configs and the password dictionary.
    #[arg(long, default_value = "secure")]
    pub out: PathBuf,
    /// Turn on mutual TLS with the certificates in this directory (`ca.pem`, `server.pem` /
    /// `.key`, `<user>.pem` / `.key`; `scripts/make-test-ca.sh` makes a throw-away set).
    #[arg(long)]
    pub tls: Option<PathBuf>,
}

/// 24 hex characters from the kernel's random source.
fn password() -> anyhow::Result<String> {
    let mut b = [0u8; 12];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut b)?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

/// Written readable by the owner only: these hold passwords.
fn private(path: &std::path::Path, text: &str) -> anyhow::Result<()> {
    write_private(path, text).with_context(|| format!("writing {}", path.display()))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mission = MissionConfig::load(args.mission.as_deref())?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let out = std::fs::canonicalize(&args.out)?;
    let tls = match &args.tls {
        Some(d) => Some(Tls {
            dir: std::fs::canonicalize(d)
                .map_err(|e| fleet_exit::bad_input(anyhow::anyhow!("--tls {}: {e}", d.display())))?,
        }),
        None => None,
    };
    let dictionary = out.join("credentials.txt");
    let mut lines = String::new();
    for user in users(&mission) {
        let pw = password()?;
        lines.push_str(&format!("{user}:{pw}\n"));
        let cfg = client_config(&mission, &user, &pw, tls.as_ref());
        private(&out.join(format!("{user}.json5")), &serde_json::to_string_pretty(&cfg)?)?;
    }
    private(&dictionary, &lines)?;
    std::fs::write(
        out.join("router.json5"),
        serde_json::to_string_pretty(&router_config(&mission, &dictionary, tls.as_ref())?)?,
    )?;
    // MAVLink signing: one key for the ground-station link, one per vehicle's autopilot link
    // (a vehicle that is taken holds only its own).
    let write_key = |dir: &std::path::Path, name: &str| -> anyhow::Result<()> {
        let (passphrase, key) = SigningKey::generate()?;
        SigningKey::write_pair(dir, name, &passphrase, &key)
            .with_context(|| format!("writing {}/{name}.key", dir.display()))
    };
    write_key(&out, "mavlink-signing")?;
    let autopilot = out.join("autopilot");
    std::fs::create_dir_all(&autopilot).with_context(|| format!("creating {}", autopilot.display()))?;
    for v in mission.vehicles() {
        write_key(&autopilot, &v.id)?;
    }
    println!(
        "wrote {}/router.json5, credentials.txt and one client config per user ({})",
        out.display(),
        users(&mission).join(", ")
    );
    println!(
        "in the mission's [network]: server_config = \"{0}/router.json5\", vehicle_config = \"{0}/{{id}}.json5\"",
        out.display()
    );
    println!(
        "wrote MAVLink signing keys {0}/mavlink-signing.key and {0}/autopilot/<id>.key (each with its \
        .passphrase for MAVProxy and QGroundControl)",
        out.display()
    );
    println!(
        "in the mission's [mavlink]: signing_key = \"{0}/mavlink-signing.key\", autopilot_signing_key = \
        \"{0}/autopilot/{{id}}.key\"",
        out.display()
    );
    Ok(())
}
