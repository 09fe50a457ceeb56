# Summary: one table of FIT % per campaign, test, channel and model
# (the "extended" rows come from discovery.json when discovery is on).


rule summary:
    input:
        expand("results/{campaign}/identify/correlation.csv", campaign=CAMPAIGNS),
        [f for f in discover_outputs() if f.endswith("discovery.json")],
    output:
        report(
            "results/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
            labels={"result": "FIT % over campaigns"},
        ),
    log:
        "logs/summary.log",
    params:
        result_dirs=lambda wildcards, input: [
            os.path.dirname(os.path.dirname(f))
            for f in input
            if f.endswith("correlation.csv")
        ],
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "mbst report summary {params.result_dirs:q} --out {output:q} > {log:q} 2>&1"


# Quick bookkeeping: on a cluster it runs on the submitting machine.
localrules:
    summary,
