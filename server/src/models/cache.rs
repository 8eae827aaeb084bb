//! The registry's cache of parsed artifacts: least recently used first out once the artifacts' size
//! passes a byte budget. (The active model, which a stream start must always find without the
//! database, is held apart by the registry and never evicted.) Sizes are the serialised artifact's bytes, a fair proxy
//! of the parsed form (a JSON float takes about as many bytes as its f64 and its share of the
//! structure). It knows nothing of the store or of gRPC.

use std::collections::HashMap;
use std::sync::Arc;

use spoofwatch_core::model::artifact::ModelArtifact;

/// One cached artifact.
#[derive(Debug)]
struct Entry {
    artifact: Arc<ModelArtifact>,
    bytes: usize,
    /// Value of the use counter at the last get or insert.
    last_used: u64,
}

/// Artifacts by model id, bounded by approximate bytes.
#[derive(Debug)]
pub struct ModelCache {
    budget_bytes: usize,
    used_bytes: usize,
    /// Increases at every use; orders the entries by recency.
    uses: u64,
    entries: HashMap<String, Entry>,
}

impl ModelCache {
    /// An empty cache that holds at most `budget_bytes` of artifacts.
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            budget_bytes,
            used_bytes: 0,
            uses: 0,
            entries: HashMap::new(),
        }
    }

    /// The artifact cached under `id`, now the most recently used.
    pub fn get(&mut self, id: &str) -> Option<Arc<ModelArtifact>> {
        self.uses += 1;
        let entry = self.entries.get_mut(id)?;
        entry.last_used = self.uses;
        Some(Arc::clone(&entry.artifact))
    }

    /// Caches `artifact` (serialised size `bytes`) under `id`, then evicts the least recently used
    /// entries until the budget holds. An artifact larger than the whole budget is not cached (it
    /// would empty the cache for nothing): callers keep their own `Arc`.
    pub fn insert(&mut self, id: &str, artifact: Arc<ModelArtifact>, bytes: usize) {
        self.remove(id);
        if bytes > self.budget_bytes {
            return;
        }
        self.uses += 1;
        self.entries.insert(
            id.to_string(),
            Entry {
                artifact,
                bytes,
                last_used: self.uses,
            },
        );
        self.used_bytes += bytes;
        while self.used_bytes > self.budget_bytes {
            let oldest = self
                .entries
                .iter()
                .min_by_key(|(_, entry)| entry.last_used)
                .map(|(id, _)| id.clone());
            match oldest {
                Some(id) => self.remove(&id),
                None => break,
            }
        }
    }

    /// Forgets `id` (a deleted model).
    pub fn remove(&mut self, id: &str) {
        if let Some(entry) = self.entries.remove(id) {
            self.used_bytes -= entry.bytes;
        }
    }

    /// Bytes of the cached artifacts.
    #[cfg(test)]
    pub fn used_bytes(&self) -> usize {
        self.used_bytes
    }

    /// Whether `id` is cached (without counting as a use).
    #[cfg(test)]
    pub fn contains(&self, id: &str) -> bool {
        self.entries.contains_key(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::registry::BUNDLED_MODEL;

    fn artifact() -> Arc<ModelArtifact> {
        Arc::new(ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model"))
    }

    #[test]
    fn the_least_recently_used_goes_first_and_bytes_add_up() {
        let model = artifact();
        let mut cache = ModelCache::new(300);
        cache.insert("a", Arc::clone(&model), 100);
        cache.insert("b", Arc::clone(&model), 100);
        cache.insert("c", Arc::clone(&model), 100);
        assert_eq!(cache.used_bytes(), 300);
        // Using "a" makes "b" the least recently used.
        assert!(cache.get("a").is_some());
        cache.insert("d", Arc::clone(&model), 100);
        assert!(!cache.contains("b"));
        assert!(cache.contains("a") && cache.contains("c") && cache.contains("d"));
        assert_eq!(cache.used_bytes(), 300);
        // A big entry pushes out as many as it needs, oldest first.
        cache.insert("e", Arc::clone(&model), 250);
        assert!(!cache.contains("c") && !cache.contains("a") && !cache.contains("d"));
        assert_eq!(cache.used_bytes(), 250);
        // An entry larger than the budget does not stay.
        cache.insert("huge", Arc::clone(&model), 301);
        assert!(!cache.contains("huge") && cache.contains("e"));
        // Replacing an entry replaces its bytes; removing frees them.
        cache.insert("e", Arc::clone(&model), 50);
        assert_eq!(cache.used_bytes(), 50);
        cache.remove("e");
        assert_eq!(cache.used_bytes(), 0);
        assert!(cache.get("e").is_none());
    }
}
