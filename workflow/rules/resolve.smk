# The MBST loop (docs/loop.md): when discovery could not decide — pairs its resolution step
# marks below resolution — design the next tests that would, on the campaign's own cut-outs
# and within its amplitude and rate limits, and write the campaign with them appended.
#
# Optional target: `snakemake --cores 2 results/<campaign>/resolve/resolve.json`, or set
# `resolve: {enabled: true}` in the config to make it part of `all` for every campaign.
# Written atomically (a temporary sibling folder renamed into place).


rule resolve:
    input:
        discovery="results/{campaign}/discover/discovery.json",
    output:
        record="results/{campaign}/resolve/resolve.json",
        campaign="results/{campaign}/resolve/campaign.yaml",
        candidates="results/{campaign}/resolve/candidates.csv",
        summary="results/{campaign}/resolve/resolve.md",
        summary_html=report(
            "results/{campaign}/resolve/resolve.html",
            caption="../report/resolve_md.rst",
            category="Next tests",
            subcategory="{campaign}",
            labels={"campaign": "{campaign}", "result": "tests that decide"},
        ),
    log:
        "logs/resolve/{campaign}.log",
    benchmark:
        "results/{campaign}/benchmarks/resolve.tsv"
    threads: 2
    params:
        outdir=lambda wildcards, output: os.path.dirname(output.record),
        budget_share=config.get("resolve", {}).get("budget_share", 0.5),
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}"
        " OPENBLAS_NUM_THREADS={threads} NUMBA_NUM_THREADS={threads}"
        " mbst plan --resolve {input.discovery:q} --budget-share {params.budget_share}"
        " --out {params.outdir:q} --quiet > {log:q} 2>&1"
