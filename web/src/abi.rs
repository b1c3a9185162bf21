//! The WebAssembly exports: `qx_*` functions on numbers, with byte buffers in the
//! module's memory. The page asks for an input buffer of `len` bytes (`qx_input`), writes
//! its bytes there, and calls; a call returns a number (negative: failed, the message is
//! the output), and leaves its bytes in the output buffer (`qx_output_ptr`,
//! `qx_output_len`), valid until the next call. `web-demo/js/wasm.mjs` is the other side.
//!
//! This is the crate's only `unsafe`-lint exception: `#[unsafe(no_mangle)]` names the
//! exports and an `unsafe extern` block declares the page's clock (a safe function). No
//! `unsafe` block exists: the page writes input bytes into a `Vec` this module owns, whose
//! address it was given, between calls.
#![allow(unsafe_code)]

use std::cell::RefCell;
use std::time::Duration;

use quincunx_client_core::refine::Clock;

use crate::api::Module;

#[link(wasm_import_module = "env")]
unsafe extern "C" {
    /// `performance.now()`, milliseconds.
    safe fn qx_now_ms() -> f64;
}

/// The page's clock (refinement's budget).
struct PageClock;

impl Clock for PageClock {
    fn now(&self) -> Duration {
        Duration::try_from_secs_f64(qx_now_ms().max(0.0) / 1000.0).unwrap_or_default()
    }
}

thread_local! {
    static MODULE: RefCell<Module> = RefCell::new(Module::default());
    static INPUT: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
    static OUTPUT: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on the module and the input's first `len` bytes; its bytes become the
/// output, its error the output and -1.
fn call<T>(
    len: u32,
    f: impl FnOnce(&mut Module, &[u8]) -> Result<(T, Vec<u8>), String>,
) -> Option<T> {
    let result = INPUT.with_borrow(|input| {
        let input = input.get(..len as usize).unwrap_or(&[]);
        MODULE.with_borrow_mut(|m| f(m, input))
    });
    match result {
        Ok((v, out)) => {
            OUTPUT.set(out);
            Some(v)
        }
        Err(e) => {
            OUTPUT.set(e.into_bytes());
            None
        }
    }
}

fn status(r: Option<i32>) -> i32 {
    r.unwrap_or(-1)
}

/// An input buffer of `len` bytes; its address.
#[unsafe(no_mangle)]
pub extern "C" fn qx_input(len: u32) -> u32 {
    INPUT.with_borrow_mut(|v| {
        v.clear();
        v.resize(len as usize, 0);
        v.as_mut_ptr() as u32
    })
}

/// The output's address.
#[unsafe(no_mangle)]
pub extern "C" fn qx_output_ptr() -> u32 {
    OUTPUT.with_borrow_mut(|v| v.as_mut_ptr() as u32)
}

/// The output's length.
#[unsafe(no_mangle)]
pub extern "C" fn qx_output_len() -> u32 {
    OUTPUT.with_borrow(|v| v.len() as u32)
}

/// Drops object `h`.
#[unsafe(no_mangle)]
pub extern "C" fn qx_free(h: u32) {
    MODULE.with_borrow_mut(|m| m.free(h));
}

/// A decoder ([`Module::decoder_new`]); its handle.
#[unsafe(no_mangle)]
pub extern "C" fn qx_decoder_new(len: u32) -> i32 {
    status(call(len, |m, i| Ok((m.decoder_new(i)? as i32, Vec::new()))))
}

/// [`Module::decoder_decode`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_decoder_decode(h: u32, len: u32) -> i32 {
    status(call(len, |m, i| Ok((0, m.decoder_decode(h, i)?))))
}

/// A client ([`Module::client_new`]); its handle.
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_new(len: u32, now_ms: f64) -> i32 {
    status(call(len, |m, i| {
        Ok((m.client_new(i, now_ms)? as i32, Vec::new()))
    }))
}

/// [`Module::client_answer`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_answer(h: u32, len: u32, now_ms: f64) -> i32 {
    status(call(len, |m, i| {
        Ok((m.client_answer(h, i, now_ms)?, Vec::new()))
    }))
}

/// [`Module::client_decoded`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_decoded(h: u32, len: u32, now_ms: f64) -> i32 {
    status(call(len, |m, i| {
        Ok((m.client_decoded(h, i, now_ms).map(|()| 0)?, Vec::new()))
    }))
}

/// [`Module::client_decode_failed`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_decode_failed(h: u32, len: u32, now_ms: f64) -> i32 {
    status(call(len, |m, i| {
        Ok((
            m.client_decode_failed(h, i, now_ms).map(|()| 0)?,
            Vec::new(),
        ))
    }))
}

/// [`Module::client_frame`], the budget read from the page's clock.
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_frame(h: u32, len: u32, now_ms: f64, budget_ms: f64) -> i32 {
    status(call(len, |m, i| {
        Ok((
            m.client_frame(h, i, now_ms, budget_ms, &PageClock)?,
            Vec::new(),
        ))
    }))
}

/// [`Module::client_plan`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_plan(h: u32, now_ms: f64) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_plan(h, now_ms)?))))
}

/// [`Module::client_wake_in`]: milliseconds, -1 for never, -2 on failure.
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_wake_in(h: u32, now_ms: f64) -> f64 {
    call(0, |m, _| Ok((m.client_wake_in(h, now_ms)?, Vec::new()))).unwrap_or(-2.0)
}

/// [`Module::client_changes`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_changes(h: u32) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_changes(h)?))))
}

/// [`Module::client_restart`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_restart(h: u32) -> i32 {
    status(call(0, |m, _| {
        Ok((m.client_restart(h).map(|()| 0)?, Vec::new()))
    }))
}

/// [`Module::client_set_max_cut_halves`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_set_max_cut_halves(h: u32, max: f64) -> i32 {
    status(call(0, |m, _| {
        Ok((m.client_set_max_cut_halves(h, max).map(|()| 0)?, Vec::new()))
    }))
}

/// [`Module::client_info`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_info(h: u32) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_info(h)?))))
}

/// [`Module::client_stats`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_stats(h: u32) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_stats(h)?))))
}

/// [`Module::client_check`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_check(h: u32) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_check(h)?))))
}

/// [`Module::client_height_range`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_client_height_range(h: u32) -> i32 {
    status(call(0, |m, _| Ok((0, m.client_height_range(h)?))))
}

/// [`Module::reconstruct`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_reconstruct(len: u32, decoder: u32) -> i32 {
    status(call(len, |m, i| {
        Ok((0, m.reconstruct(i, decoder, &PageClock)?))
    }))
}

/// [`Module::pack_first`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_pack_first(len: u32) -> i32 {
    status(call(len, |m, i| Ok((0, m.pack_first(i)?))))
}

/// A repository file's reader ([`Module::pack_new`]); its handle.
#[unsafe(no_mangle)]
pub extern "C" fn qx_pack_new(len: u32) -> i32 {
    status(call(len, |m, i| {
        let (h, out) = m.pack_new(i)?;
        Ok((h as i32, out))
    }))
}

/// [`Module::pack_plan`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_pack_plan(h: u32, len: u32) -> i32 {
    status(call(len, |m, i| Ok((0, m.pack_plan(h, i)?))))
}

/// [`Module::pack_answered`].
#[unsafe(no_mangle)]
pub extern "C" fn qx_pack_answered(h: u32, len: u32) -> i32 {
    status(call(len, |m, i| Ok((0, m.pack_answered(h, i)?))))
}
