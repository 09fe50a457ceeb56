# Virtual test bench: for campaigns with a `bench:` recipe in the config, write
# a campaign in the mbst-campaign/1 format plus its ground truth (truth.json,
# beside the campaign, never inside it). Campaigns with `path:` skip this step.


rule bench:
    output:
        campaign=directory("results/{campaign}/bench/campaign"),
        truth="results/{campaign}/bench/truth.json",
    log:
        "logs/bench/{campaign}.log",
    wildcard_constraints:
        campaign=alternation(BENCH_CAMPAIGNS),
    params:
        outdir=lambda wildcards, output: os.path.dirname(output.truth),
        effects=bench_effect_args,
        sensors=bench_sensor_arg,
        seed=lambda wildcards: bench_recipe(wildcards)["seed"],
        noise_scale=lambda wildcards: bench_recipe(wildcards)["noise_scale"],
        plan=lambda wildcards: bench_recipe(wildcards)["plan"],
        assist=lambda wildcards: bench_recipe(wildcards)["assist_characteristic"],
        code=CODE_VERSION,
    conda:
        "../envs/mbst.yaml"
    shell:
        "mbst bench --out {params.outdir:q} --name {wildcards.campaign:q}"
        " {params.effects} --seed {params.seed} --noise-scale {params.noise_scale}"
        " --sensors {params.sensors} --plan {params.plan} --assist-characteristic {params.assist}"
        " > {log:q} 2>&1"
