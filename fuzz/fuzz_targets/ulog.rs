//! Fuzz target `ulog`: see `fuzz/entry.rs` for what it calls and asserts (ULog reader).
#![no_main]

#[allow(dead_code)]
#[path = "../entry.rs"]
mod entry;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = entry::ulog(data);
});
