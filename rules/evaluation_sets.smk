# Generated scan sets of the generation tables (rules/evaluation.smk): each set is a
# list of sample shard folders made by parallel `omnilidar sample` jobs (rule sample_eval),
# so a table only scores and a failure loses one shard. Needs rules/generator.smk first.

SINGLE_DOMAIN = f"{DATA}/generator_single"
EVAL_SHARD = config["generator"]["sampling"]["scans_per_shard"]


def eval_checkpoint(model):
    """Generator of an evaluation set: a preset (full, cdts, ...), baseline-<Domain>, or `student`
    (the full preset's distilled student)."""
    if model.startswith("baseline-"):
        return f"{SINGLE_DOMAIN}/{model[len('baseline-'):]}/model.pt"
    if model == "student":
        return f"{GENERATOR}/full/student.pt"
    return f"{GENERATOR}/{model}/model.pt"


def eval_sample_shards(model, domain, sampler, steps, count, reuse=True):
    """Shard folders holding the first ``count`` scans of one generated set; with ``reuse`` the
    generator's own samples where the setting is the generator's own sampler (their quality is the
    same, their seconds per scan were timed in another job and batch, so a timing study does not
    reuse them)."""
    shards = -(-int(count) // EVAL_SHARD)
    gen = config["generator"]["sampling"]
    if (reuse and model == "full" and (sampler, int(steps)) == (gen["sampler"], gen["steps"])
            and count <= gen["scans_per_domain"]):
        return sample_shards(domain)[:shards]
    return [f"{DATA}/eval_samples/{model}/{sampler}_{steps}/{domain}/shard_{k}" for k in range(shards)]


def generated_sets(sets, reuse=True):
    """{key: shard folders} of several sets given as {key: (model, domain, sampler, steps, count)}."""
    return {key: eval_sample_shards(*spec, reuse=reuse) for key, spec in sets.items()}


def sets_args(sets):
    return " ".join(f"--samples {key}={d}" for key, dirs in sets.items() for d in dirs)


def table_sets(models, domains):
    """{prefix/Domain: shards} of the tables' sets (evaluation sampler, steps, scans_per_set);
    ``models`` maps a key prefix to a model, or to a function of the domain giving one."""
    ev = config["evaluation"]
    return generated_sets({f"{prefix}/{d}": (m(d) if callable(m) else m, d, ev["sampler"], ev["steps"], ev["scans_per_set"])
                           for prefix, m in models.items() for d in domains})


def eval_sampling_settings(sampler, steps):
    """The generator section as `omnilidar sample` reads it, with the evaluation's sampler,
    steps, batch and device. Like sample_domain's, without the distillation settings: a student's
    sets change with its checkpoint (an input), a teacher's do not change with them at all."""
    gen = json.loads(settings("generator", drop=("distillation",)))
    ev = config["evaluation"]
    gen["sampling"].update(sampler=sampler, steps=int(steps), batch_size=ev["batch_size"], device=ev["device"],
                           student=False)
    return json.dumps(gen, sort_keys=True)
