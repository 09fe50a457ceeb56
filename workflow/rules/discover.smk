# Discovery: find what the base model lacks, name the effect and its component,
# insert it, refit, and compare model families on the held-out control tests
# (base, extended, SINDy-only, physics + neural residual, physics + the learned
# term of an unexplained finding, and the bench's true model when the campaign
# came from the virtual bench).
#
# Same atomic pattern as identify.smk: write into discover.tmp, rename when done.
# Discovery starts from the identify rule's cascade (`--base-fit`, its base_fit.json)
# instead of fitting the same deterministic cascade again; `mbst discover` checks that
# the record was made from this campaign's data with these settings by this code, and
# fits the cascade itself where it was not.


rule discover:
    input:
        campaign=campaign_inputs,
        base_fit="results/{campaign}/identify/base_fit.json",
    output:
        discovery="results/{campaign}/discover/discovery.json",
        comparison=report(
            "results/{campaign}/discover/comparison.csv",
            caption="../report/comparison.rst",
            category="Discovery",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "control FIT per model family"},
        ),
        summary="results/{campaign}/discover/discovery.md",
        resolution="results/{campaign}/discover/resolution.csv",
        summary_html=report(
            "results/{campaign}/discover/discovery.html",
            caption="../report/discovery_md.rst",
            category="Discovery",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "findings"},
        ),
        figures=report(
            directory("results/{campaign}/discover/figures"),
            patterns=["{name}.png"],
            caption="../report/discover_figures.rst",
            category="Discovery",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "figure: {name}"},
        ),
    log:
        "logs/discover/{campaign}.log",
    benchmark:
        "results/{campaign}/benchmarks/discover.tsv"
    threads: 2
    params:
        campaign_dir=campaign_dir,
        outdir=lambda wildcards, output: os.path.dirname(output.discovery),
        tmpdir=lambda wildcards, output: f"{os.path.dirname(output.discovery)}.tmp",
        tau_s=config["preprocess"]["tau_s"],
        seed=config["identify"]["seed"],
        multistart=config["identify"]["multistart"],
        joint="--joint" if config["identify"].get("joint_refinement") else "",
        max_effects=discover_setting("max_effects"),
        min_gain=discover_setting("min_relative_gain"),
        aic_margin=aic_margin_arg,
        skip=discover_skip_args,
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "rm -rf {params.tmpdir:q} {params.outdir:q}"
        " && OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}"
        " OPENBLAS_NUM_THREADS={threads} NUMBA_NUM_THREADS={threads}"
        " mbst discover {params.campaign_dir:q} --out {params.tmpdir:q} --quiet"
        " --tau {params.tau_s} --seed {params.seed} --multistart {params.multistart} {params.joint}"
        " --max-effects {params.max_effects} --min-gain {params.min_gain}"
        " --base-fit {input.base_fit:q}"
        " {params.aic_margin} {params.skip}"
        " > {log:q} 2>&1"
        " && rm -rf {params.outdir:q}"
        " && mv {params.tmpdir:q} {params.outdir:q}"
