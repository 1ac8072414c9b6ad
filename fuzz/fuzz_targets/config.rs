//! The config loader: `config::Config::from_toml_str` on arbitrary text, then `validate()`.
//! A config is accepted whole and valid, or refused with an error that names a key.
#![no_main]

use imucald::config::Config;
use imucald::error::Error;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    match Config::from_toml_str(text) {
        Ok(cfg) => {
            // Accepted means valid, and stays so.
            cfg.validate().expect("an accepted config validates");
            let _ = cfg.declination_deg();
            for s in &cfg.daemon.sources {
                imucald::link::Address::parse(&s.address).expect("validated address");
            }
        }
        Err(Error::Config { key, message }) => {
            assert!(!key.is_empty() && !message.is_empty(), "{key:?}: {message:?}");
        }
        Err(other) => panic!("not a config error: {other}"),
    }
});
