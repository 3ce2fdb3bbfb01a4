//! Avatars kept in memory under a byte budget, the least recently used dropped first. Ids are
//! content addresses of the uploaded photo, so the same photo finds its avatar again.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use gagavatar_avatar::Avatar;
use gagavatar_flame::TrackedFrame;

/// A reconstructed avatar and what the page shows of it.
pub struct Stored {
    pub avatar: Arc<Avatar>,
    /// The tracked 512 crop, as PNG.
    pub crop_png: Vec<u8>,
    pub record: TrackedFrame,
    /// Bytes counted against the budget (Gaussians + crop).
    pub bytes: usize,
}

struct Entry {
    stored: Arc<Stored>,
    last_used: u64,
}

struct Inner {
    entries: HashMap<String, Entry>,
    clock: u64,
    bytes: usize,
}

pub struct AvatarStore {
    inner: Mutex<Inner>,
    budget: usize,
}

impl AvatarStore {
    pub fn new(budget: usize) -> Self {
        AvatarStore {
            inner: Mutex::new(Inner {
                entries: HashMap::new(),
                clock: 0,
                bytes: 0,
            }),
            budget,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The avatar `id`, marked as just used.
    pub fn get(&self, id: &str) -> Option<Arc<Stored>> {
        let mut g = self.lock();
        g.clock += 1;
        let now = g.clock;
        let e = g.entries.get_mut(id)?;
        e.last_used = now;
        Some(e.stored.clone())
    }

    /// Keeps `stored` as `id`, then drops the least recently used others until the total fits
    /// the budget (the new one stays even if it alone is over). Returns how many were dropped.
    pub fn insert(&self, id: &str, stored: Arc<Stored>) -> usize {
        let mut g = self.lock();
        g.clock += 1;
        let now = g.clock;
        let add = stored.bytes;
        if let Some(old) = g.entries.insert(
            id.to_owned(),
            Entry {
                stored,
                last_used: now,
            },
        ) {
            g.bytes -= old.stored.bytes;
        }
        g.bytes += add;
        let mut dropped = 0;
        while g.bytes > self.budget && g.entries.len() > 1 {
            let Some(victim) = g
                .entries
                .iter()
                .filter(|(k, _)| k.as_str() != id)
                .min_by_key(|(_, e)| e.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            if let Some(e) = g.entries.remove(&victim) {
                g.bytes -= e.stored.bytes;
                dropped += 1;
            }
        }
        dropped
    }

    pub fn remove(&self, id: &str) -> bool {
        let mut g = self.lock();
        match g.entries.remove(id) {
            Some(e) => {
                g.bytes -= e.stored.bytes;
                true
            }
            None => false,
        }
    }

    /// (avatars, bytes) held now.
    pub fn usage(&self) -> (usize, usize) {
        let g = self.lock();
        (g.entries.len(), g.bytes)
    }
}
